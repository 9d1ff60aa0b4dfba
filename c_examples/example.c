/*
 * nsdd C example: both levels of the C ABI, checked against analytic values.
 *
 * 1. Scene level: a symmetric two-bar truss with a vertical cable below the
 *    loaded node, built from arrays. Pushed down, the cable goes slack and the
 *    bars carry the load (u_y = -P L / (2 EA sin^2 45°), T = P / (2 sin 45°));
 *    pulled up, the cable works in parallel with the bars. Solved with the
 *    direct method and with multilevel DD on 2 subdomains.
 * 2. Algebraic level: a chain of 8 springs along x, fixed at node 0, split by
 *    hand into 2 subdomains assembled here in CSR, with a unilateral cable from
 *    the last node to a wall on its right. Set up once, solved for two loads.
 *
 * Build and run: make -C c_examples run (exit status 0 when every check passes).
 */
#include "nsdd.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int failures = 0;

/* Prints the last error and exits when a call fails. */
static void check_status(NsddStatus st, const char *what) {
    if (st != NSDD_STATUS_OK) {
        size_t n = nsdd_last_error_message(NULL, 0);
        char *msg = malloc(n);
        nsdd_last_error_message(msg, n);
        fprintf(stderr, "%s failed: %s: %s\n", what, nsdd_status_name((int32_t)st), msg);
        free(msg);
        exit(2);
    }
}

static void expect(const char *what, double got, double want, double tol) {
    int ok = fabs(got - want) <= tol * fmax(1.0, fabs(want));
    printf("  %-34s % .10f (expected % .10f) %s\n", what, got, want, ok ? "ok" : "WRONG");
    if (!ok) failures++;
}

/* ---- scene level ------------------------------------------------------- */

static void solve_truss(NsddScene *scene, const NsddOptions *opts, double fy, double *u2y, double *t,
                        uint8_t *slack) {
    const size_t load_node[1] = {2};
    const double fx[1] = {0.0}, fys[1] = {fy}, fz[1] = {0.0};
    check_status(nsdd_scene_set_loads(scene, 1, load_node, fx, fys, fz), "nsdd_scene_set_loads");

    NsddResult *res = NULL;
    check_status(nsdd_solve(scene, opts, &res), "nsdd_solve");
    size_t nn = 0, ne = 0, iters = 0;
    bool converged = false;
    check_status(nsdd_result_num_nodes(res, &nn), "nsdd_result_num_nodes");
    check_status(nsdd_result_num_elements(res, &ne), "nsdd_result_num_elements");
    check_status(nsdd_result_iterations(res, &iters), "nsdd_result_iterations");
    check_status(nsdd_result_converged(res, &converged), "nsdd_result_converged");
    uint32_t why = 0;
    check_status(nsdd_result_stop_reason(res, &why), "nsdd_result_stop_reason");
    if ((why == NSDD_STOP_REASON_CONVERGED) != converged) failures++;
    /* How far the tensions miss equilibrium with the loads (relative to
       their norm): a converged solve holds it within its tolerance. */
    double eq = 0.0;
    check_status(nsdd_result_equilibrium_residual(res, &eq), "nsdd_result_equilibrium_residual");
    size_t corrections = 0, correction_iters = 0;
    check_status(nsdd_result_equilibrium_corrections(res, &corrections, &correction_iters),
                 "nsdd_result_equilibrium_corrections");
    printf("  tensions off the loads by %.2e of their norm (%zu equilibrium corrections, %zu iterations)\n", eq,
           corrections, correction_iters);
    if (converged && !(eq <= 1e-6)) failures++;
    double *u = malloc(3 * nn * sizeof(double));
    check_status(nsdd_result_displacements(res, u, 3 * nn), "nsdd_result_displacements");
    check_status(nsdd_result_tensions(res, t, ne), "nsdd_result_tensions");
    check_status(nsdd_result_slack(res, slack, ne), "nsdd_result_slack");
    size_t hl = 0;
    check_status(nsdd_result_history_len(res, &hl), "nsdd_result_history_len");
    double *ind = malloc((hl ? hl : 1) * sizeof(double));
    check_status(nsdd_result_history(res, ind, NULL, hl), "nsdd_result_history");
    printf("  %zu nodes, %zu elements, %zu iterations, converged %d, final indicator %.2e\n", nn, ne, iters,
           (int)converged, hl ? ind[hl - 1] : 0.0);
    if (!converged) failures++;
    *u2y = u[3 * 2 + 1];
    free(ind);
    free(u);
    nsdd_result_destroy(res);
}

static void scene_level(void) {
    const double EA = 1000.0, P = 10.0, s45 = sqrt(0.5), L = sqrt(2.0);
    NsddScene *scene = nsdd_scene_new();
    if (!scene) exit(2);
    const double x[4] = {-1.0, 1.0, 0.0, 0.0};
    const double y[4] = {1.0, 1.0, 0.0, -1.0};
    const double z[4] = {0.0, 0.0, 0.0, 0.0};
    check_status(nsdd_scene_set_nodes(scene, 4, x, y, z), "nsdd_scene_set_nodes");
    const size_t a[3] = {0, 1, 2}, b[3] = {2, 2, 3};
    const uint8_t kind[3] = {NSDD_ELEMENT_KIND_BAR, NSDD_ELEMENT_KIND_BAR, NSDD_ELEMENT_KIND_CABLE};
    const double ea[3] = {EA, EA, EA};
    check_status(nsdd_scene_set_elements(scene, 3, a, b, kind, ea, NULL), "nsdd_scene_set_elements");
    const size_t sn[4] = {0, 1, 3, 2};
    const uint8_t mask[4] = {7, 7, 7, NSDD_SUPPORT_Z};
    check_status(nsdd_scene_set_supports(scene, 4, sn, mask), "nsdd_scene_set_supports");
    check_status(nsdd_scene_set_effects(scene, true, false, false, false), "nsdd_scene_set_effects");
    check_status(nsdd_scene_set_name(scene, "two-bar truss with cable"), "nsdd_scene_set_name");

    NsddOptions *direct = nsdd_options_new();
    NsddOptions *multi = nsdd_options_new();
    if (!direct || !multi) exit(2);
    check_status(nsdd_options_set_method(multi, NSDD_METHOD_MULTILEVEL), "nsdd_options_set_method");
    check_status(nsdd_options_set_subdomains(multi, 2), "nsdd_options_set_subdomains");
    check_status(nsdd_options_set_tolerance(multi, 1e-12), "nsdd_options_set_tolerance");
    /* The default; NSDD_ORDERING_NESTED_DISSECTION skips the AMD trial on
       structures known to be 3D. */
    check_status(nsdd_options_set_ordering(multi, NSDD_ORDERING_AUTO), "nsdd_options_set_ordering");

    const NsddOptions *opts[2] = {direct, multi};
    const char *names[2] = {"direct", "multilevel, 2 subdomains"};
    for (int m = 0; m < 2; m++) {
        double uy, t[3];
        uint8_t slack[3];
        double tol = m == 0 ? 1e-12 : 1e-6;
        printf("scene level (%s), load pushing down: cable slack\n", names[m]);
        solve_truss(scene, opts[m], -P, &uy, t, slack);
        expect("u_y of the loaded node", uy, -P * L / (2.0 * EA * s45 * s45), tol);
        expect("bar tension", t[0], P / (2.0 * s45), tol);
        expect("cable tension", t[2], 0.0, tol);
        expect("cable slack flag", slack[2], 1.0, 0.0);

        printf("scene level (%s), load pulling up: cable taut\n", names[m]);
        solve_truss(scene, opts[m], P, &uy, t, slack);
        double k = 2.0 * EA / L * s45 * s45 + EA / 1.0;
        expect("u_y of the loaded node", uy, P / k, tol);
        expect("cable tension", t[2], EA * P / k, tol);
        expect("cable slack flag", slack[2], 0.0, 0.0);
    }
    nsdd_options_destroy(direct);
    nsdd_options_destroy(multi);
    nsdd_scene_destroy(scene);
}

/* ---- algebraic level --------------------------------------------------- */

enum { N = 8, NG = N }; /* springs, global dofs (nodes 1..N, x only) */

/* Full symmetric CSR of a small dense matrix (zeros dropped). */
static void dense_to_csr(size_t n, const double *d, size_t *row_ptr, size_t *col, double *val) {
    size_t nnz = 0;
    row_ptr[0] = 0;
    for (size_t i = 0; i < n; i++) {
        for (size_t j = 0; j < n; j++) {
            if (d[i * n + j] != 0.0) {
                col[nnz] = j;
                val[nnz] = d[i * n + j];
                nnz++;
            }
        }
        row_ptr[i + 1] = nnz;
    }
}

/* Adds a spring of stiffness k between local dofs i and j (j < 0: fixed). */
static void add_spring(size_t n, double *d, int i, int j, double k) {
    d[i * n + i] += k;
    if (j >= 0) {
        d[j * n + j] += k;
        d[i * n + j] -= k;
        d[j * n + i] -= k;
    }
}

static void algebraic_level(void) {
    const double k = 100.0, kc = 50.0;
    NsddAlgebraic *alg = NULL;
    check_status(nsdd_alg_new(2, NG, &alg), "nsdd_alg_new");

    /* Subdomain 0: springs 1..4 (node 0 fixed), nodes 1..4 = global dofs 0..3. */
    {
        double d[16] = {0};
        add_spring(4, d, 0, -1, k);
        for (int i = 1; i < 4; i++) add_spring(4, d, i, i - 1, k);
        size_t rp[5], col[16], l2g[4] = {0, 1, 2, 3};
        double val[16];
        dense_to_csr(4, d, rp, col, val);
        check_status(nsdd_alg_set_subdomain(alg, 0, 4, rp, col, val, l2g), "nsdd_alg_set_subdomain 0");
    }
    /* Subdomain 1: springs 5..8, nodes 8, 7, 6, 5, 4 in this (reversed) local
     * order = global dofs 7..3, plus the cable's stiffness at node 8. */
    {
        double d[25] = {0};
        for (int i = 0; i < 4; i++) add_spring(5, d, i, i + 1, k);
        add_spring(5, d, 0, -1, kc);
        size_t rp[6], col[25], l2g[5] = {7, 6, 5, 4, 3};
        double val[25];
        dense_to_csr(5, d, rp, col, val);
        check_status(nsdd_alg_set_subdomain(alg, 1, 5, rp, col, val, l2g), "nsdd_alg_set_subdomain 1");
        /* Cable from node 8 to the wall on its right: elongation = -u_8. */
        size_t cdof[1] = {0}, idx = 99;
        double coef[1] = {-1.0};
        check_status(nsdd_alg_add_cable(alg, 1, 1, cdof, coef, kc, 0.0, &idx), "nsdd_alg_add_cable");
        if (idx != 0) failures++;
    }
    double xyz[3 * NG];
    uint8_t comp[NG];
    for (int g = 0; g < NG; g++) {
        xyz[3 * g] = g + 1.0;
        xyz[3 * g + 1] = xyz[3 * g + 2] = 0.0;
        comp[g] = 0;
    }
    check_status(nsdd_alg_set_dof_points(alg, NG, xyz, comp), "nsdd_alg_set_dof_points");

    NsddOptions *opts = nsdd_options_new();
    if (!opts) exit(2);
    check_status(nsdd_options_set_method(opts, NSDD_METHOD_MULTILEVEL), "nsdd_options_set_method");
    check_status(nsdd_options_set_tolerance(opts, 1e-12), "nsdd_options_set_tolerance");
    check_status(nsdd_alg_setup(alg, opts), "nsdd_alg_setup");
    nsdd_options_destroy(opts);

    for (int c = 0; c < 2; c++) {
        const double P = c == 0 ? 1.0 : -1.0;
        double rhs0[4] = {0}, rhs1[5] = {0};
        rhs1[0] = P; /* local 0 of subdomain 1 is node 8 */
        const double *rhs[2] = {rhs0, rhs1};
        double u[NG], lambda[1];
        size_t iters = 0;
        bool conv = false;
        check_status(nsdd_alg_solve(alg, rhs, u, lambda, &iters, &conv), "nsdd_alg_solve");
        printf("algebraic level, P = %+.0f at the end node (%s): %zu iterations, converged %d\n", P,
               c == 0 ? "cable slack" : "cable taut", iters, (int)conv);
        if (!conv) failures++;
        if (c == 0) {
            expect("u of node 4", u[3], 4.0 * P / k, 1e-8);
            expect("u of node 8", u[7], N * P / k, 1e-8);
            expect("cable slack lambda", lambda[0], N * P / k, 1e-8);
        } else {
            double u8 = P / (k / N + kc);
            expect("u of node 4", u[3], u8 * 4.0 / N, 1e-8);
            expect("u of node 8", u[7], u8, 1e-8);
            expect("cable slack lambda", lambda[0], 0.0, 1e-8);
        }
    }
    nsdd_alg_destroy(alg);
}

int main(void) {
    printf("nsdd %s (C example)\n", nsdd_version());
    scene_level();
    algebraic_level();

    /* A deliberate error, to show the status and message. */
    NsddAlgebraic *bad = NULL;
    NsddStatus st = nsdd_alg_new(0, 10, &bad);
    char msg[128];
    nsdd_last_error_message(msg, sizeof msg);
    printf("expected error: %s: %s\n", nsdd_status_name((int32_t)st), msg);
    if (st != NSDD_STATUS_INVALID_ARGUMENT || bad != NULL) failures++;

    if (failures) {
        printf("%d check(s) FAILED\n", failures);
        return 1;
    }
    printf("all checks passed\n");
    return 0;
}
