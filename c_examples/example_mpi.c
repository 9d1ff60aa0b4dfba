/* The algebraic level of nsdd under MPI: a chain of N springs (node 0
 * fixed, a force P at node N, an optional cable from node N to a wall)
 * cut into S subdomains of M springs, spread over the ranks of
 * MPI_COMM_WORLD. Each rank sets only its own subdomains (nsdd_alg_owned),
 * as an FE code under MPI holds them, and every rank gets the whole
 * displacement, checked against the analytic values.
 *
 *   make -C c_examples mpi     # builds nsdd with --features mpi, runs this with mpirun -np 2
 */
#include "nsdd.h"

#include <math.h>
#include <mpi.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum { S = 4, M = 4, N = S * M };

static int failures = 0;
static int rank = 0, size = 1;

static void check_status(NsddStatus st, const char *what) {
    if (st != NSDD_STATUS_OK) {
        size_t n = nsdd_last_error_message(NULL, 0);
        char *msg = malloc(n);
        nsdd_last_error_message(msg, n);
        fprintf(stderr, "rank %d: %s failed: %s: %s\n", rank, what, nsdd_status_name((int32_t)st), msg);
        free(msg);
        MPI_Abort(MPI_COMM_WORLD, 2);
    }
}

static void expect(const char *what, double got, double want, double tol) {
    int ok = fabs(got - want) <= tol * fmax(1.0, fabs(want));
    if (rank == 0) printf("  %-30s % .10f (expected % .10f) %s\n", what, got, want, ok ? "ok" : "WRONG");
    if (!ok) failures++;
}

/* Subdomain s: springs s*M+1 .. s*M+M (spring j joins nodes j-1 and j);
 * its local dof l is node s*M + l (subdomain 0 has no dof for the fixed
 * node 0: its local l is node l + 1). Global dof of node i is i - 1. */
static void set_subdomain(NsddAlgebraic *alg, int s, double k, double kc_end) {
    const int first = s == 0 ? 1 : s * M; /* first node with a dof */
    const int n = s * M + M - first + 1;  /* local dofs */
    double d[(M + 1) * (M + 1)] = {0};
    for (int j = s * M + 1; j <= s * M + M; j++) {
        int a = j - 1 - first, b = j - first; /* local dofs of the ends (-1: fixed) */
        d[b * n + b] += k;
        if (a >= 0) {
            d[a * n + a] += k;
            d[a * n + b] -= k;
            d[b * n + a] -= k;
        }
    }
    if (s == S - 1) d[(n - 1) * n + (n - 1)] += kc_end; /* the cable's stiffness at node N */
    size_t rp[M + 2], col[(M + 1) * (M + 1)], l2g[M + 1];
    double val[(M + 1) * (M + 1)];
    size_t nnz = 0;
    for (int i = 0; i < n; i++) {
        rp[i] = nnz;
        for (int j = 0; j < n; j++)
            if (d[i * n + j] != 0.0) {
                col[nnz] = (size_t)j;
                val[nnz++] = d[i * n + j];
            }
        l2g[i] = (size_t)(first + i - 1);
    }
    rp[n] = nnz;
    check_status(nsdd_alg_set_subdomain(alg, (size_t)s, (size_t)n, rp, col, val, l2g), "nsdd_alg_set_subdomain");
    if (s == S - 1 && kc_end > 0.0) {
        /* Cable from node N to the wall on its right: elongation = -u_N. */
        size_t dof[1] = {(size_t)(n - 1)}, idx = 99;
        double coef[1] = {-1.0};
        check_status(nsdd_alg_add_cable(alg, (size_t)s, 1, dof, coef, kc_end, 0.0, &idx), "nsdd_alg_add_cable");
    }
}

static void chain(uint32_t method, double kc) {
    const double k = 100.0;
    NsddAlgebraic *alg = NULL;
    check_status(nsdd_alg_new_mpi(S, N, MPI_Comm_c2f(MPI_COMM_WORLD), &alg), "nsdd_alg_new_mpi");
    size_t first = 0, count = 0;
    check_status(nsdd_alg_owned(alg, &first, &count), "nsdd_alg_owned");
    for (size_t s = first; s < first + count; s++) set_subdomain(alg, (int)s, k, kc);
    double xyz[3 * N];
    uint8_t comp[N];
    for (int g = 0; g < N; g++) {
        xyz[3 * g] = g + 1.0;
        xyz[3 * g + 1] = xyz[3 * g + 2] = 0.0;
        comp[g] = 0;
    }
    check_status(nsdd_alg_set_dof_points(alg, N, xyz, comp), "nsdd_alg_set_dof_points");
    NsddOptions *opts = nsdd_options_new();
    if (!opts) MPI_Abort(MPI_COMM_WORLD, 2);
    check_status(nsdd_options_set_method(opts, method), "nsdd_options_set_method");
    check_status(nsdd_options_set_tolerance(opts, 1e-12), "nsdd_options_set_tolerance");
    check_status(nsdd_alg_setup(alg, opts), "nsdd_alg_setup");
    nsdd_options_destroy(opts);
    size_t nc = 0;
    check_status(nsdd_alg_num_cables(alg, &nc), "nsdd_alg_num_cables");
    if (nc != (kc > 0.0 ? 1u : 0u)) failures++;

    for (int c = 0; c < (kc > 0.0 ? 2 : 1); c++) {
        const double P = c == 0 ? 1.0 : -1.0;
        /* This rank's right-hand sides: P on node N, in the last subdomain. */
        double rhs_store[S][M + 1] = {{0}};
        const double *rhs[S];
        for (size_t i = 0; i < count; i++) {
            size_t s = first + i;
            if (s == S - 1) rhs_store[i][M] = P;
            rhs[i] = rhs_store[i];
        }
        double u[N], lambda[1] = {0};
        size_t iters = 0;
        bool conv = false;
        check_status(nsdd_alg_solve(alg, rhs, u, lambda, &iters, &conv), "nsdd_alg_solve");
        if (rank == 0)
            printf("%s, P = %+.0f%s: %zu iterations, converged %d\n",
                   method == NSDD_METHOD_CG ? "cg" : "multilevel", P,
                   kc > 0.0 ? (c == 0 ? " (cable slack)" : " (cable taut)") : "", iters, (int)conv);
        if (!conv) failures++;
        /* Tension t in every spring; u_i = t i / k. */
        double t = (kc > 0.0 && c == 1) ? P * (k / N) / (k / N + kc) : P;
        for (int i = 1; i <= N; i++) {
            double want = t * i / k;
            if (fabs(u[i - 1] - want) > 1e-8 * fabs(P * N / k)) {
                failures++;
                if (rank == 0) printf("  u of node %d: %.12f, expected %.12f WRONG\n", i, u[i - 1], want);
            }
        }
        expect("u of node N", u[N - 1], t * N / k, 1e-8);
        if (kc > 0.0) expect("cable slack lambda", lambda[0], c == 0 ? N * P / k : 0.0, 1e-8);
        if (kc == 0.0) {
            /* A NULL right-hand side on the last rank only: every rank gets
             * its status and message back (none waits in the solve). */
            const double *bad[S];
            for (size_t i = 0; i < count; i++) bad[i] = rhs[i];
            if (rank == size - 1) bad[0] = NULL;
            NsddStatus st = nsdd_alg_solve(alg, bad, u, NULL, NULL, NULL);
            size_t n = nsdd_last_error_message(NULL, 0);
            char *msg = malloc(n);
            nsdd_last_error_message(msg, n);
            int ok = st == NSDD_STATUS_NULL_POINTER && strstr(msg, "rhs[") != NULL;
            if (!ok) failures++;
            if (rank == 0)
                printf("  NULL rhs on rank %d only: rank 0 gets %s (%s) %s\n", size - 1,
                       nsdd_status_name((int32_t)st), msg, ok ? "ok" : "WRONG");
            free(msg);
        }
    }
    nsdd_alg_destroy(alg);
}

int main(int argc, char **argv) {
    int level = 0;
    MPI_Init_thread(&argc, &argv, MPI_THREAD_FUNNELED, &level);
    MPI_Comm_rank(MPI_COMM_WORLD, &rank);
    MPI_Comm_size(MPI_COMM_WORLD, &size);
    if (rank == 0) printf("nsdd algebraic level on %d MPI ranks, %d subdomains\n", size, S);
    chain(NSDD_METHOD_CG, 0.0);
    chain(NSDD_METHOD_MULTILEVEL, 50.0);
    /* Every rank checked the whole displacement: any failure fails all. */
    int all = 0;
    MPI_Allreduce(&failures, &all, 1, MPI_INT, MPI_SUM, MPI_COMM_WORLD);
    if (rank == 0) printf("%s\n", all == 0 ? "all checks passed" : "SOME CHECKS FAILED");
    MPI_Finalize();
    return all == 0 ? 0 : 1;
}
