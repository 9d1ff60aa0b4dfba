// nsdd C++ example: the C ABI from C++, with RAII owners for the handles.
//
// 1. Scene level: the two-bar truss of SCENE.md style read from TOML text,
//    solved with its own [solver] settings, then the same scene built from
//    arrays; both checked against the analytic answer.
// 2. Algebraic level: a chain of 12 springs along x split into 3 subdomains
//    (the middle one floats: its matrix is singular and the multilevel method
//    handles its kernel), with a unilateral cable at the free end, assembled
//    in CSR here and solved for two loads on one set-up.
//
// Build and run: make -C c_examples run (exit status 0 when every check passes).
#include "nsdd.h"

#include <cmath>
#include <cstdio>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

namespace {

struct SceneDel { void operator()(NsddScene *p) const { nsdd_scene_destroy(p); } };
struct ResultDel { void operator()(NsddResult *p) const { nsdd_result_destroy(p); } };
struct OptionsDel { void operator()(NsddOptions *p) const { nsdd_options_destroy(p); } };
struct AlgDel { void operator()(NsddAlgebraic *p) const { nsdd_alg_destroy(p); } };
using Scene = std::unique_ptr<NsddScene, SceneDel>;
using Result = std::unique_ptr<NsddResult, ResultDel>;
using Options = std::unique_ptr<NsddOptions, OptionsDel>;
using Alg = std::unique_ptr<NsddAlgebraic, AlgDel>;

// Throws with the library's message when a call fails.
void check(NsddStatus st, const char *what) {
    if (st != NSDD_STATUS_OK) {
        std::string msg(nsdd_last_error_message(nullptr, 0), '\0');
        nsdd_last_error_message(&msg[0], msg.size());
        msg.resize(msg.size() - 1);
        throw std::runtime_error(std::string(what) + ": " + nsdd_status_name(st) + ": " + msg);
    }
}

int failures = 0;

void expect(const char *what, double got, double want, double tol) {
    bool ok = std::fabs(got - want) <= tol * std::fmax(1.0, std::fabs(want));
    std::printf("  %-34s % .10f (expected % .10f) %s\n", what, got, want, ok ? "ok" : "WRONG");
    if (!ok) failures++;
}

const char *kTruss = R"(
[scene]
name = "two-bar truss"

[effects]
unilateral_cables = true

[solver]
method = "multilevel"
subdomains = 2
tolerance = 1e-12

[nodes]
x = [-1.0, 1.0, 0.0]
y = [1.0, 1.0, 0.0]
z = [0.0, 0.0, 0.0]

[elements]
a = [0, 1]
b = [2, 2]
kind = ["bar", "cable"]
ea = [1000.0, 1000.0]

[supports]
node = [0, 1, 2]
dofs = ["xyz", "xyz", "z"]

[loads]
node = [2]
fy = [-10.0]
)";

void check_truss(const NsddScene *scene, const char *label) {
    const double EA = 1000.0, P = 10.0, s45 = std::sqrt(0.5), L = std::sqrt(2.0);
    NsddResult *raw = nullptr;
    check(nsdd_solve(scene, nullptr, &raw), "nsdd_solve");
    Result res(raw);
    size_t nn = 0, ne = 0, iters = 0;
    bool conv = false;
    check(nsdd_result_num_nodes(res.get(), &nn), "num_nodes");
    check(nsdd_result_num_elements(res.get(), &ne), "num_elements");
    check(nsdd_result_iterations(res.get(), &iters), "iterations");
    check(nsdd_result_converged(res.get(), &conv), "converged");
    std::vector<double> u(3 * nn), t(ne);
    std::vector<uint8_t> slack(ne);
    check(nsdd_result_displacements(res.get(), u.data(), u.size()), "displacements");
    check(nsdd_result_tensions(res.get(), t.data(), t.size()), "tensions");
    check(nsdd_result_slack(res.get(), slack.data(), slack.size()), "slack");
    std::printf("scene level (%s): %zu iterations, converged %d\n", label, iters, int(conv));
    if (!conv) failures++;
    // Both elements hang the node: cable (element 1) in tension, not slack.
    expect("u_y of the loaded node", u[3 * 2 + 1], -P * L / (2 * EA * s45 * s45), 1e-6);
    expect("bar tension", t[0], P / (2 * s45), 1e-6);
    expect("cable tension", t[1], P / (2 * s45), 1e-6);
    expect("cable slack flag", slack[1], 0.0, 0.0);
}

void scene_level() {
    NsddScene *raw = nullptr;
    check(nsdd_scene_from_str(kTruss, false, &raw), "nsdd_scene_from_str");
    Scene from_text(raw);
    check_truss(from_text.get(), "from TOML text, multilevel");

    Scene built(nsdd_scene_new());
    if (!built) throw std::runtime_error("nsdd_scene_new");
    const double x[] = {-1, 1, 0}, y[] = {1, 1, 0}, z[] = {0, 0, 0};
    const size_t a[] = {0, 1}, b[] = {2, 2};
    const uint8_t kind[] = {NSDD_ELEMENT_KIND_BAR, NSDD_ELEMENT_KIND_CABLE};
    const double ea[] = {1000, 1000};
    const size_t sn[] = {0, 1, 2};
    const uint8_t mask[] = {7, 7, NSDD_SUPPORT_Z};
    const size_t ln[] = {2};
    const double fx[] = {0}, fy[] = {-10}, fz[] = {0};
    check(nsdd_scene_set_nodes(built.get(), 3, x, y, z), "set_nodes");
    check(nsdd_scene_set_elements(built.get(), 2, a, b, kind, ea, nullptr), "set_elements");
    check(nsdd_scene_set_supports(built.get(), 3, sn, mask), "set_supports");
    check(nsdd_scene_set_loads(built.get(), 1, ln, fx, fy, fz), "set_loads");
    check(nsdd_scene_set_effects(built.get(), true, false, false, false), "set_effects");
    check_truss(built.get(), "from arrays, direct");
}

// Full symmetric CSR of a chain segment: local dof i is node first + i.
struct Csr {
    std::vector<size_t> row_ptr, col;
    std::vector<double> val;
};

Csr chain_csr(const std::vector<std::vector<double>> &d) {
    Csr c;
    c.row_ptr.push_back(0);
    for (size_t i = 0; i < d.size(); i++) {
        for (size_t j = 0; j < d.size(); j++) {
            if (d[i][j] != 0.0) {
                c.col.push_back(j);
                c.val.push_back(d[i][j]);
            }
        }
        c.row_ptr.push_back(c.col.size());
    }
    return c;
}

void algebraic_level() {
    const int N = 12;          // springs; nodes 0..N, node 0 fixed
    const double k = 200.0, kc = 40.0;
    const int cuts[] = {0, 4, 8, 12};  // subdomain s holds springs cuts[s]+1..cuts[s+1]
    NsddAlgebraic *raw = nullptr;
    check(nsdd_alg_new(3, N, &raw), "nsdd_alg_new");  // global dof g = node g + 1
    Alg alg(raw);
    for (int s = 0; s < 3; s++) {
        int first = cuts[s] == 0 ? 1 : cuts[s];  // first free node of the subdomain
        int n = cuts[s + 1] - first + 1;
        std::vector<std::vector<double>> d(n, std::vector<double>(n, 0.0));
        for (int e = cuts[s] + 1; e <= cuts[s + 1]; e++) {  // spring between nodes e-1 and e
            int i = e - first, j = e - 1 - first;
            d[i][i] += k;
            if (j >= 0) {
                d[j][j] += k;
                d[i][j] -= k;
                d[j][i] -= k;
            }
        }
        if (s == 2) d[n - 1][n - 1] += kc;  // the cable's stiffness at node N
        Csr c = chain_csr(d);
        std::vector<size_t> l2g(n);
        for (int i = 0; i < n; i++) l2g[i] = size_t(first + i - 1);
        check(nsdd_alg_set_subdomain(alg.get(), s, n, c.row_ptr.data(), c.col.data(), c.val.data(), l2g.data()),
              "nsdd_alg_set_subdomain");
        if (s == 2) {
            size_t dof[] = {size_t(n - 1)};
            double coef[] = {-1.0};  // cable to a wall on the right: elongation -u_N
            check(nsdd_alg_add_cable(alg.get(), 2, 1, dof, coef, kc, 0.0, nullptr), "nsdd_alg_add_cable");
        }
    }
    std::vector<double> xyz(3 * N, 0.0);
    std::vector<uint8_t> comp(N, 0);
    for (int g = 0; g < N; g++) xyz[3 * g] = g + 1.0;
    check(nsdd_alg_set_dof_points(alg.get(), N, xyz.data(), comp.data()), "nsdd_alg_set_dof_points");
    Options opts(nsdd_options_new());
    check(nsdd_options_set_method(opts.get(), NSDD_METHOD_MULTILEVEL), "set_method");
    check(nsdd_options_set_tolerance(opts.get(), 1e-12), "set_tolerance");
    check(nsdd_alg_setup(alg.get(), opts.get()), "nsdd_alg_setup");
    double d = 0;
    check(nsdd_alg_search_direction(alg.get(), &d), "nsdd_alg_search_direction");
    std::printf("algebraic level: 3 subdomains, search direction d = %.4g\n", d);

    for (double P : {1.0, -1.0}) {
        // Global right-hand side: the solver splits shared dofs itself.
        std::vector<double> f(N, 0.0), u(N);
        f[N - 1] = P;
        double lambda = -1;
        size_t iters = 0;
        bool conv = false;
        check(nsdd_alg_solve_global(alg.get(), f.data(), u.data(), &lambda, &iters, &conv), "nsdd_alg_solve_global");
        std::printf("algebraic level, P = %+.0f (%s): %zu iterations, converged %d\n", P,
                    P > 0 ? "cable slack" : "cable taut", iters, int(conv));
        if (!conv) failures++;
        double uN = P > 0 ? N * P / k : P / (k / N + kc);
        expect("u of node 6", u[5], uN * 6.0 / N, 1e-8);
        expect("u of node 12", u[N - 1], uN, 1e-8);
        expect("cable slack lambda", lambda, P > 0 ? uN : 0.0, 1e-8);
    }
}

}  // namespace

int main() {
    std::printf("nsdd %s (C++ example)\n", nsdd_version());
    try {
        scene_level();
        algebraic_level();
        // A deliberate error: unknown method value.
        Options o(nsdd_options_new());
        try {
            check(nsdd_options_set_method(o.get(), 7), "nsdd_options_set_method");
            failures++;
        } catch (const std::exception &e) {
            std::printf("expected error: %s\n", e.what());
        }
    } catch (const std::exception &e) {
        std::fprintf(stderr, "%s\n", e.what());
        return 2;
    }
    if (failures) {
        std::printf("%d check(s) FAILED\n", failures);
        return 1;
    }
    std::printf("all checks passed\n");
    return 0;
}
