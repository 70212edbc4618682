/* The MPC's per-cycle numerics in one call: the condensed QP's vectors from the cycle's
 * inputs, OSQP's update, warm start and solve (the embedded solver OSQP generated for the
 * shipped QP, see tools/generate_mpc_solver.py), the solution's checks and the plan.  Loaded by
 * truckd/control/ccycle.py; the same arithmetic as truckd/control/condensed.py (fill,
 * plan) and truckd/control/mpc.py (solve) in Python.
 *
 * OSQP's generated workspaces are static: TRUCKD_MPC_INSTANCES of them (each a solver
 * per mode), which ccycle.py hands to one MPC solver each. */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "osqp.h"
#include "lin_alg.h"
#include "algebra_vector.h"
#include "types.h"
#include "algebra_impl.h"
#include "instances.h"
#include "mpc_cycle.h"

#if TRUCKD_MPC_MODES > 2
#error "truckd_mpc_run passes the mode in one bit"
#endif

static OSQPSolver *const SOLVERS[TRUCKD_MPC_INSTANCES][TRUCKD_MPC_MODES] = TRUCKD_MPC_SOLVERS;

static OSQPSolver *solver_of(int64_t inst, int64_t mode) {
    if (inst < 0 || inst >= TRUCKD_MPC_INSTANCES || mode < 0 || mode >= TRUCKD_MPC_MODES)
        return NULL;
    return SOLVERS[inst][mode];
}

/* Where each instance's per-cycle products and plan find their matrices (owned by
 * Python). */
static struct {
    const double *f_span;  /* 4 keys (mode * 2 + lead), each span_len x ns, row-major */
    const double *f_const; /* 4 keys, each span_len x n_const */
    double *buf;           /* [u; q; l] of the QP, nw + 2 m */
    int64_t span_start, span_len, ns, n_const;
    const double *plan_v; /* (horizon + 1) x (nw + nx) */
    const int64_t *u_block;
    int64_t horizon, nx;
    int bound;
    /* the cycle's inputs and outputs (truckd_mpc_bind_io): values, two (x, y) pairs, the
     * plan (u, v) and info */
    const double *values;
    double *x[2], *y[2], *u, *v, *info;
    int bound_io;
    /* the plan to publish (truckd_mpc_bind_plan): the speeds v clipped at 0 (N + 1),
     * then their differences over dt (N + 1, the last repeated); dt in s */
    double *plan;
    double plan_dt;
} BOUND[TRUCKD_MPC_INSTANCES];

/* OSQP's linear system, solved reduced and dense.  OSQP's KKT system
 *     [P + sigma I, A'; A, -diag(1/rho)] [x; nu] = [b1; b2]
 * (n + m = 147 rows, its sparse LDL factor has some 900 nonzeros, solved twice per
 * iteration: half of OSQP's instructions) is, with nu = rho (A x - b2),
 *     (P + sigma I + A' diag(rho) A) x = b1 + A' (rho b2),   z~ = b2 + nu / rho = A x
 * an n x n system (n = 10): its Cholesky factor is computed when rho or the matrices
 * change (where OSQP refactors its KKT matrix), and each solve is two dense products
 * with A and two triangular solves.  The same iterates as OSQP's own solver up to
 * rounding (tests/test_mpc_compiled.py compares the commands). */
/* A's rows padded to a multiple of 8 for the product z~ = A x (below) */
#define TRUCKD_MPC_MP ((TRUCKD_MPC_M + 7) / 8 * 8)

typedef struct {
    double a[TRUCKD_MPC_M * TRUCKD_MPC_N]; /* OSQP's scaled A, row-major */
    double at[TRUCKD_MPC_N * TRUCKD_MPC_MP]; /* the same, column-major, zero rows padded */
    double l[TRUCKD_MPC_N * TRUCKD_MPC_N]; /* Cholesky factor (lower) of the reduced matrix */
    double rho[TRUCKD_MPC_M];
    OSQPSolver *solver;
} Dense;

static Dense DENSE[TRUCKD_MPC_INSTANCES][TRUCKD_MPC_MODES];

static Dense *dense_of(const LinSysSolver *ls) {
    for (int64_t i = 0; i < TRUCKD_MPC_INSTANCES; ++i)
        for (int64_t k = 0; k < TRUCKD_MPC_MODES; ++k)
            if (SOLVERS[i][k]->work->linsys_solver == ls) return &DENSE[i][k];
    return NULL;
}

static void dense_load_a(Dense *d) {
    const OSQPCscMatrix *a = d->solver->work->data->A->csc;
    memset(d->a, 0, sizeof d->a);
    memset(d->at, 0, sizeof d->at);
    for (OSQPInt j = 0; j < a->n; ++j)
        for (OSQPInt k = a->p[j]; k < a->p[j + 1]; ++k) {
            d->a[a->i[k] * TRUCKD_MPC_N + j] = a->x[k];
            d->at[j * TRUCKD_MPC_MP + a->i[k]] = a->x[k];
        }
}

/* The reduced matrix from OSQP's scaled P (upper triangle) and A, factored. */
static OSQPInt dense_factor(Dense *d) {
    enum { N = TRUCKD_MPC_N, M = TRUCKD_MPC_M };
    double k[N * N];
    const OSQPCscMatrix *p = d->solver->work->data->P->csc;
    double sigma = d->solver->settings->sigma;
    memset(k, 0, sizeof k);
    for (OSQPInt j = 0; j < p->n; ++j)
        for (OSQPInt q = p->p[j]; q < p->p[j + 1]; ++q) {
            OSQPInt i = p->i[q];
            k[i * N + j] += p->x[q];
            if (i != j) k[j * N + i] += p->x[q];
        }
    for (int i = 0; i < N; ++i) k[i * N + i] += sigma;
    for (int r = 0; r < M; ++r) {
        const double *row = d->a + r * N;
        for (int i = 0; i < N; ++i) {
            double ri = d->rho[r] * row[i];
            if (ri == 0.0) continue;
            for (int j = 0; j < N; ++j) k[i * N + j] += ri * row[j];
        }
    }
    for (int j = 0; j < N; ++j) { /* Cholesky, lower, in place into d->l */
        double s = k[j * N + j];
        for (int q = 0; q < j; ++q) s -= d->l[j * N + q] * d->l[j * N + q];
        if (!(s > 0.0)) return 1;
        double ljj = sqrt(s);
        d->l[j * N + j] = ljj;
        for (int i = j + 1; i < N; ++i) {
            double t = k[i * N + j];
            for (int q = 0; q < j; ++q) t -= d->l[i * N + q] * d->l[j * N + q];
            d->l[i * N + j] = t / ljj;
        }
        for (int i = 0; i < j; ++i) d->l[i * N + j] = 0.0;
    }
    return 0;
}

/* The dense products below on x86-64 in two builds chosen when the library loads (GCC's
 * target clones, glibc's ifunc): AVX where the CPU has it (four doubles per instruction),
 * else the baseline.
 * The same operations in the same order in each lane and no contraction into fused
 * multiply-adds (-std=c99: ISO C's -ffp-contract=off): the same numbers either way. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && defined(__GLIBC__)
#define TRUCKD_VECTOR_CLONES __attribute__((target_clones("avx", "default")))
#else
#define TRUCKD_VECTOR_CLONES
#endif

/* y = A x over the dense copy (y: M values), eight rows at a time over A's columns: each
 * row's sum in the order of j, as a dot product of the row and OSQP's column loop take it
 * (the same numbers), in registers across j. */
TRUCKD_VECTOR_CLONES
static void dense_ax(const Dense *d, const double *x, double *y) {
    enum { N = TRUCKD_MPC_N, M = TRUCKD_MPC_M, MP = TRUCKD_MPC_MP };
    for (int i0 = 0; i0 < MP; i0 += 8) {
        double t[8] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        for (int j = 0; j < N; ++j) {
            const double *col = d->at + j * MP + i0;
            double xj = x[j];
            for (int q = 0; q < 8; ++q) t[q] += col[q] * xj;
        }
        int rows = M - i0 < 8 ? M - i0 : 8;
        for (int q = 0; q < rows; ++q) y[i0 + q] = t[q];
    }
}

TRUCKD_VECTOR_CLONES
static OSQPInt dense_solve(LinSysSolver *ls, OSQPVectorf *b, OSQPInt admm_iter) {
    enum { N = TRUCKD_MPC_N, M = TRUCKD_MPC_M, MP = TRUCKD_MPC_MP };
    Dense *d = dense_of(ls);
    double r[N], x[N];
    double *bv = b->values;
    (void)admm_iter;
    if (d == NULL) return 1;
    for (int j = 0; j < N; ++j) r[j] = bv[j];
    for (int i = 0; i < M; ++i) {
        double w = d->rho[i] * bv[N + i];
        const double *row = d->a + i * N;
        for (int j = 0; j < N; ++j) r[j] += row[j] * w;
    }
    for (int i = 0; i < N; ++i) { /* L y = r */
        double t = r[i];
        for (int q = 0; q < i; ++q) t -= d->l[i * N + q] * x[q];
        x[i] = t / d->l[i * N + i];
    }
    for (int i = N - 1; i >= 0; --i) { /* L' x = y */
        double t = x[i];
        for (int q = i + 1; q < N; ++q) t -= d->l[q * N + i] * x[q];
        x[i] = t / d->l[i * N + i];
    }
    for (int j = 0; j < N; ++j) bv[j] = x[j];
    dense_ax(d, x, bv + N); /* z~ = A x */
    return 0;
}

/* The dense copy of the A whose products OSQP asks for (y = A x or A' x, alpha 1, beta 0:
 * the residuals of every termination check), or NULL: OSQP's sparse product then. */
static const Dense *dense_product_of(const OSQPMatrix *a, OSQPFloat alpha, OSQPFloat beta) {
    if (alpha != 1.0 || beta != 0.0) return NULL;
    for (int64_t i = 0; i < TRUCKD_MPC_INSTANCES; ++i)
        for (int64_t k = 0; k < TRUCKD_MPC_MODES; ++k)
            if (DENSE[i][k].solver != NULL && DENSE[i][k].solver->work->data->A == a)
                return &DENSE[i][k];
    return NULL;
}

/* Called by OSQP's generated OSQPMatrix_Axpy (tools/generate_mpc_solver.py): y = A x over
 * the dense copy, each row's sum in the order of the columns as OSQP's column loop adds it
 * (zeros added as +-0: the same numbers).  1: done, 0: OSQP's own product. */
OSQPInt truckd_dense_Axpy(const OSQPMatrix *a, const OSQPFloat *x, OSQPFloat *y, OSQPFloat alpha,
                          OSQPFloat beta);
OSQPInt truckd_dense_Axpy(const OSQPMatrix *a, const OSQPFloat *x, OSQPFloat *y, OSQPFloat alpha,
                          OSQPFloat beta) {
    const Dense *d = dense_product_of(a, alpha, beta);
    if (d == NULL) return 0;
    dense_ax(d, x, y);
    return 1;
}

/* The same for OSQPMatrix_Atxpy: y = A' x, each column's sum in the order of the rows. */
OSQPInt truckd_dense_Atxpy(const OSQPMatrix *a, const OSQPFloat *x, OSQPFloat *y, OSQPFloat alpha,
                           OSQPFloat beta);
OSQPInt truckd_dense_Atxpy(const OSQPMatrix *a, const OSQPFloat *x, OSQPFloat *y, OSQPFloat alpha,
                           OSQPFloat beta) {
    enum { N = TRUCKD_MPC_N, M = TRUCKD_MPC_M };
    const Dense *d = dense_product_of(a, alpha, beta);
    if (d == NULL) return 0;
    double r[N];
    for (int j = 0; j < N; ++j) r[j] = 0.0;
    for (int i = 0; i < M; ++i) {
        double w = x[i];
        const double *row = d->a + i * N;
        for (int j = 0; j < N; ++j) r[j] += row[j] * w;
    }
    for (int j = 0; j < N; ++j) y[j] = r[j];
    return 1;
}

static OSQPInt dense_update_rho(LinSysSolver *ls, const OSQPVectorf *rho_vec, OSQPFloat rho_sc) {
    Dense *d = dense_of(ls);
    if (d == NULL) return 1;
    for (int i = 0; i < TRUCKD_MPC_M; ++i) d->rho[i] = rho_vec != NULL ? rho_vec->values[i] : rho_sc;
    return dense_factor(d);
}

static OSQPInt dense_update_matrices(LinSysSolver *ls, const OSQPMatrix *p, const OSQPInt *pi,
                                     OSQPInt pn, const OSQPMatrix *a, const OSQPInt *ai,
                                     OSQPInt an) {
    Dense *d = dense_of(ls);
    (void)p, (void)pi, (void)pn, (void)a, (void)ai, (void)an;
    if (d == NULL) return 1;
    dense_load_a(d);
    return dense_factor(d);
}

/* The solver's linear system from now on dense (its current rho and matrices). */
static OSQPInt dense_install(int64_t inst, int64_t mode) {
    Dense *d = &DENSE[inst][mode];
    OSQPSolver *s = SOLVERS[inst][mode];
    LinSysSolver *ls = s->work->linsys_solver;
    if (s->work->data->n != TRUCKD_MPC_N || s->work->data->m != TRUCKD_MPC_M) return 1;
    d->solver = s;
    for (int i = 0; i < TRUCKD_MPC_M; ++i) d->rho[i] = s->work->rho_vec->values[i];
    dense_load_a(d);
    if (dense_factor(d) != 0) return 1;
    ls->solve = dense_solve;
    ls->update_rho_vec = dense_update_rho;
    ls->update_matrices = dense_update_matrices;
    return 0;
}

int64_t truckd_mpc_abi(void) { return TRUCKD_MPC_ABI; }

int64_t truckd_mpc_instances(void) { return TRUCKD_MPC_INSTANCES; }

/* The generated sizes: [n, m, nnz P follow, nnz A follow, nnz P cruise, nnz A cruise]
 * (the same for every instance). */
void truckd_mpc_shape(int64_t *out) {
    for (int64_t k = 0; k < TRUCKD_MPC_MODES; ++k) {
        OSQPSolver *s = solver_of(0, k);
        OSQPCscMatrix *p = s->work->data->P->csc;
        OSQPCscMatrix *a = s->work->data->A->csc;
        out[0] = a->n;
        out[1] = a->m;
        out[2 + 2 * k] = p->p[p->n];
        out[3 + 2 * k] = a->p[a->n];
    }
}

/* The sparsity pattern of one mode's P (upper triangle) and A, as int64 arrays of the
 * sizes truckd_mpc_shape gives. */
void truckd_mpc_pattern(int64_t mode, int64_t *pp, int64_t *pi, int64_t *ap, int64_t *ai) {
    OSQPSolver *s = solver_of(0, mode);
    OSQPCscMatrix *p = s->work->data->P->csc;
    OSQPCscMatrix *a = s->work->data->A->csc;
    for (OSQPInt j = 0; j <= p->n; ++j) pp[j] = p->p[j];
    for (OSQPInt k = 0; k < p->p[p->n]; ++k) pi[k] = p->i[k];
    for (OSQPInt j = 0; j <= a->n; ++j) ap[j] = a->p[j];
    for (OSQPInt k = 0; k < a->p[a->n]; ++k) ai[k] = a->i[k];
}

/* This truck's matrix values (same pattern), vectors and settings into one mode's solver:
 * the vectors first, so that OSQP's scaling (of the cost too, which depends on q) is
 * computed from this truck's problem, as a setup would. */
int64_t truckd_mpc_setup(int64_t inst, int64_t mode, const double *px, const double *ax,
                         const double *q, const double *l, const double *u, double eps_abs,
                         double eps_rel, int64_t max_iter, int64_t check_termination,
                         double time_limit, double rho, double alpha, int64_t rho_interval,
                         double rho_tolerance) {
    OSQPSolver *s = solver_of(inst, mode);
    if (s == NULL) return -1;
    /* The ADMM's settings from the caller (truckd.control.mpc.osqp_settings), not the ones
     * the generated code was made with: one source for both paths. */
    s->settings->alpha = alpha;
    s->settings->adaptive_rho_interval = (OSQPInt)rho_interval;
    s->settings->adaptive_rho_tolerance = rho_tolerance;
    s->settings->eps_abs = eps_abs;
    s->settings->eps_rel = eps_rel;
    s->settings->max_iter = (OSQPInt)max_iter;
    s->settings->check_termination = (OSQPInt)check_termination;
    s->settings->time_limit = time_limit;
    /* OSQP's scaling to one first: the vectors and matrices then arrive unrounded by the
     * previous owner's scaling (or the generated truck's), and the scaling computed from
     * them is a setup's, whatever the instance solved before (bit for bit: a simulation
     * run twice in one process gives the same results). */
    if (s->settings->scaling) {
        OSQPScaling *sc = s->work->scaling;
        sc->c = 1.0;
        sc->cinv = 1.0;
        OSQPVectorf_set_scalar(sc->D, 1.0);
        OSQPVectorf_set_scalar(sc->Dinv, 1.0);
        OSQPVectorf_set_scalar(sc->E, 1.0);
        OSQPVectorf_set_scalar(sc->Einv, 1.0);
    }
    OSQPInt flag = osqp_update_data_vec(s, q, l, u);
    if (flag != 0) return (int64_t)flag;
    flag = osqp_update_data_mat(s, px, OSQP_NULL, 0, ax, OSQP_NULL, 0);
    if (flag != 0) return (int64_t)flag;
    flag = osqp_update_rho(s, rho);
    if (flag != 0) return (int64_t)flag;
    return dense_install(inst, mode) == 0 ? 0 : -4;
}

int64_t truckd_mpc_set_max_iter(int64_t inst, int64_t mode, int64_t max_iter) {
    OSQPSolver *s = solver_of(inst, mode);
    if (s == NULL || max_iter < 1) return -1;
    s->settings->max_iter = (OSQPInt)max_iter;
    return 0;
}

int64_t truckd_mpc_update_rho(int64_t inst, int64_t mode, double rho) {
    OSQPSolver *s = solver_of(inst, mode);
    return s == NULL ? -1 : (int64_t)osqp_update_rho(s, rho);
}

int64_t truckd_mpc_bind(int64_t inst, const double *f_span, const double *f_const, double *buf,
                     int64_t span_start, int64_t span_len, int64_t ns, int64_t n_const,
                     const double *plan_v, const int64_t *u_block, int64_t horizon,
                     int64_t nx) {
    if (solver_of(inst, 0) == NULL) return -1;
#define B BOUND[inst]
    B.f_span = f_span;
    B.f_const = f_const;
    B.buf = buf;
    B.span_start = span_start;
    B.span_len = span_len;
    B.ns = ns;
    B.n_const = n_const;
    B.plan_v = plan_v;
    B.u_block = u_block;
    B.horizon = horizon;
    B.nx = nx;
    B.bound = 1;
#undef B
    return 0;
}

/* dst[r] = sum_c f[r, c] src[c], in order of c (as numpy's dot for one row). */
static void product(const double *f, int64_t rows, int64_t cols, const double *src,
                    double *dst) {
    for (int64_t r = 0; r < rows; ++r) {
        const double *row = f + r * cols;
        double acc = 0.0;
        for (int64_t c = 0; c < cols; ++c) acc += row[c] * src[c];
        dst[r] = acc;
    }
}

/* One cycle: values = [x0; scalars; v_lead] (ns, checked by the caller); warm_x/warm_y
 * the warm start (NULL: cold, from zero).  Out: x (n), y (m), u (horizon), v
 * (horizon + 1), info = [status_val, iterations, run time (s), all finite (1/0)].
 * Returns OSQP's status value, or a negative number when the call itself is wrong. */
int64_t truckd_mpc_cycle(int64_t inst, int64_t mode, int64_t lead, int64_t one_lead_speed,
                         const double *values, const double *warm_x, const double *warm_y,
                         double *x, double *y, double *u, double *v, double *info) {
    OSQPSolver *s = solver_of(inst, mode);
    if (s == NULL || !BOUND[inst].bound || lead < 0 || lead > 1) return -1;
#define B BOUND[inst]
    OSQPInt n = s->work->data->n, m = s->work->data->m;
    int64_t key = mode * 2 + lead;
    double *dst = B.buf + B.span_start;
    if (one_lead_speed)
        product(B.f_const + key * B.span_len * B.n_const, B.span_len, B.n_const, values, dst);
    else
        product(B.f_span + key * B.span_len * B.ns, B.span_len, B.ns, values, dst);
    OSQPInt flag = osqp_update_data_vec(s, B.buf + m, B.buf + m + n, B.buf);
    if (flag != 0) return -2;
    if (warm_x != NULL && warm_y != NULL) {
        flag = osqp_warm_start(s, warm_x, warm_y);
    } else {
        memset(x, 0, sizeof(double) * (size_t)n);
        memset(y, 0, sizeof(double) * (size_t)m);
        flag = osqp_warm_start(s, x, y);
    }
    if (flag != 0) return -3;
    osqp_solve(s);
    info[2] = s->info->run_time;
    double sum = 0.0;
    for (OSQPInt k = 0; k < n; ++k) {
        x[k] = s->solution->x[k];
        sum += x[k];
    }
    for (OSQPInt k = 0; k < m; ++k) {
        y[k] = s->solution->y[k];
        sum += y[k];
    }
    info[0] = (double)s->info->status_val;
    info[1] = (double)s->info->iter;
    info[3] = isfinite(sum) ? 1.0 : 0.0;
    /* the plan: each step's input its block's; the speeds one product with [w; x0] */
    for (int64_t k = 0; k < B.horizon; ++k) u[k] = x[B.u_block[k]];
    int64_t cols = n + B.nx;
    for (int64_t r = 0; r <= B.horizon; ++r) {
        const double *row = B.plan_v + r * cols;
        double acc = 0.0;
        for (OSQPInt c = 0; c < n; ++c) acc += row[c] * x[c];
        for (int64_t c = 0; c < B.nx; ++c) acc += row[n + c] * values[c];
        v[r] = acc;
    }
#undef B
    return (int64_t)s->info->status_val;
}

/* The plan (truckd_mpc_bind_plan's array) of the speeds in the bound v, as
 * truckd/control/platoon.py's plan_of_array makes it: each speed clipped at 0 as
 * `x < 0 ? 0 : x` (NaN and -0.0 kept), the accelerations (v[k + 1] - v[k]) / dt of the
 * clipped speeds, the last repeated (the same IEEE operations: the same numbers).
 * truckd_mpc_run calls it after each cycle.  0, or -1 without a bound plan. */
int64_t truckd_mpc_plan(int64_t inst);
int64_t truckd_mpc_plan(int64_t inst) {
    if (solver_of(inst, 0) == NULL || !BOUND[inst].bound_io || BOUND[inst].plan == NULL)
        return -1;
    const int64_t n = BOUND[inst].horizon + 1;
    const double *v = BOUND[inst].v;
    double *pv = BOUND[inst].plan, *pa = BOUND[inst].plan + n;
    const double dt = BOUND[inst].plan_dt;
    for (int64_t k = 0; k < n; ++k) pv[k] = v[k] < 0.0 ? 0.0 : v[k];
    for (int64_t k = 0; k + 1 < n; ++k) pa[k] = (pv[k + 1] - pv[k]) / dt;
    pa[n - 1] = n > 1 ? pa[n - 2] : 0.0;
    return 0;
}

/* The arrays truckd_mpc_run reads and writes (owned by Python, as in truckd_mpc_cycle):
 * values, the two (x, y) pairs (one the warm start, the other the solution), u, v, info. */
int64_t truckd_mpc_bind_io(int64_t inst, const double *values, double *x0, double *y0,
                           double *x1, double *y1, double *u, double *v, double *info) {
    if (solver_of(inst, 0) == NULL) return -1;
    BOUND[inst].values = values;
    BOUND[inst].x[0] = x0;
    BOUND[inst].y[0] = y0;
    BOUND[inst].x[1] = x1;
    BOUND[inst].y[1] = y1;
    BOUND[inst].u = u;
    BOUND[inst].v = v;
    BOUND[inst].info = info;
    BOUND[inst].plan = NULL; /* until truckd_mpc_bind_plan: none of an earlier owner's */
    BOUND[inst].bound_io = 1;
    return 0;
}

/* truckd_mpc_cycle on the bound arrays, its small arguments in one integer (a call from
 * Python converts two arguments instead of twelve): bit 0 the mode, bit 1 lead, bit 2 one
 * lead speed, bit 3 warm, bit 4 the pair holding the warm start (the solution goes into
 * the other). */
int64_t truckd_mpc_run(int64_t inst, int64_t how) {
    if (solver_of(inst, 0) == NULL || !BOUND[inst].bound_io || how < 0 || how > 31) return -1;
    int cur = (int)((how >> 4) & 1), out = 1 - cur;
    int warm = (int)((how >> 3) & 1);
    int64_t status = truckd_mpc_cycle(
        inst, how & 1, (how >> 1) & 1, (how >> 2) & 1, BOUND[inst].values,
        warm ? BOUND[inst].x[cur] : NULL, warm ? BOUND[inst].y[cur] : NULL, BOUND[inst].x[out],
        BOUND[inst].y[out], BOUND[inst].u, BOUND[inst].v, BOUND[inst].info);
    if (status >= 0) truckd_mpc_plan(inst);
    return status;
}

/* Where truckd_mpc_run writes the plan of each cycle (2 (horizon + 1) doubles, see
 * BOUND), and the plan's step dt (s); plan NULL: none written.  0, or -1 for a wrong
 * instance or dt. */
int64_t truckd_mpc_bind_plan(int64_t inst, double *plan, double dt) {
    if (solver_of(inst, 0) == NULL) return -1;
    if (!(dt > 0.0)) {
        BOUND[inst].plan = NULL;
        return -1;
    }
    BOUND[inst].plan = plan;
    BOUND[inst].plan_dt = dt;
    return 0;
}
