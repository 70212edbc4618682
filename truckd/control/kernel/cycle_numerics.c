/* The controller's per-cycle numerics around the MPC in the same call as its solve: the
 * friction feedforward, the QP's initial state and inputs with their checks, the MPC cycle
 * (mpc_cycle.c: fill, warm start, OSQP's solve, plan), then the command: breakaway at rest,
 * no reversing from rest, finite, rate limit, the voltage limit.  The same arithmetic, in
 * the same order, as truckd/control/controller.py (_feedforward, _initial_state, _solve,
 * _finish), truckd/control/feedforward.py, truckd/control/fallback.py (limit_command),
 * truckd/control/qp.py (first_move_bounds, inputs_ok) and truckd/control/condensed.py
 * (gather): tests/test_cycle_numerics.py compares the commands of both paths.
 *
 * truckd_cycle_run puts the estimator's update (estimator.c) and the controller's decisions
 * before them in the same call: Controller.control's speed check, standstill hold entry,
 * mode, offset-free action and the lead's speeds (truckd/control/lead.py), as in Python;
 * a decision that only Python takes (no valid speed, the hold) returns after the estimate.
 *
 * Every constant (the motor's, the limits, the tolerances) comes from Python when it binds
 * (truckd/control/cnumerics.py): none is written here.  Used only for models whose
 * feedforward has no torque terms but aero drag and a constant load (no terrain, no
 * Stribeck curve), without an input delay and without the driver's maps
 * (the controller checks; the others run in Python). */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#include "instances.h"
#include "mpc_cycle.h"

/* The constants, in the order truckd/control/cnumerics.py's CONSTANTS names them. */
enum {
    C_R_M,         /* winding resistance (ohm) */
    C_K_T,         /* torque constant (N m/A) */
    C_COULOMB,     /* Coulomb friction (N m) */
    C_K_V,         /* back-EMF constant (V s/rad) */
    C_RATIO,       /* speed per motor speed (m/rad) */
    C_MOVING,      /* moving_speed (m/s) */
    C_FF_ON,       /* feedforward on (1) or off (0) */
    C_BREAKAWAY,   /* the breakaway feedforward at resistance R_m (V) */
    C_START_V,     /* start_voltage (V) */
    C_U_MAX,       /* the driver's voltage limit (V) */
    C_DU,          /* the rate limit per period (V) */
    C_V_MAX,       /* v_max (m/s) */
    C_INPUT_LIMIT, /* the QP's inputs' magnitude limit */
    C_BUDGET,      /* the solve's time budget (s) */
    C_HAS_DRAG,    /* the feedforward has the aero drag term (1) or not (0) */
    C_AERO,        /* its coefficient (N/(m/s)^2) */
    C_HAS_LOAD,    /* the feedforward has the constant load term (1) or not (0) */
    C_LOAD,        /* its force (N) */
    C_D0,          /* d_0 (m) */
    C_HEADWAY,     /* time_headway, the QP's (s) */
    C_WINDOW,      /* follow_window (m) */
    C_V_SET,       /* v_set (m/s) */
    C_CRUISE_LOST, /* on_lead_lost is cruise (1) or stop (0) */
    C_HOLD_LEAD,   /* hold_lead_speed (m/s) */
    C_HOLD_GAP,    /* hold_gap_tol (m) */
    C_DIST_GAIN,   /* disturbance_gain (per cycle) */
    C_DIST_MAX,    /* disturbance_max (V) */
    C_B_V,         /* speed per volt over one step (m/s/V) */
    C_SATURATED,   /* controller.SATURATED_V (V) */
    C_COUNT
};

/* The cycle's inputs (in) and outputs (out), see truckd/control/cnumerics.py. */
enum { I_V, I_GAP, I_APPLIED, I_DIST, I_R_SCALE, I_U_HI, I_V_REF, I_LEAD0 };
enum { O_U, O_FF, O_ACTING, O_FINISHED };

/* The status returned for inputs refused before the solve (qp.inputs_ok). */
#define TRUCKD_NUMERICS_BAD_INPUT (-100)

enum { NX = 3, N_SCALARS = 8 };

static struct {
    double c[C_COUNT];
    double *in; /* written by truckd_cycle_run's decisions */
    double *values, *out;
    const double *d_in; /* the decisions' inputs and outputs (truckd_cycle_bind) */
    double *d_out;
    const double *u, *info; /* the MPC cycle's plan and info (truckd_mpc_bind_io's) */
    int64_t horizon;
    int bound;
} NUM[TRUCKD_MPC_INSTANCES];

int64_t truckd_numerics_consts(void) { return C_COUNT; }

/* The constants (copied), and the arrays each cycle reads and writes (owned by Python):
 * in (I_LEAD0 + horizon), values (the MPC cycle's inputs, NX + N_SCALARS + horizon), out
 * (4), the plan's u and the MPC cycle's info. */
int64_t truckd_numerics_bind(int64_t inst, const double *consts, int64_t n_consts,
                             double *in, double *values, double *out, const double *u,
                             const double *info, int64_t horizon) {
    if (inst < 0 || inst >= TRUCKD_MPC_INSTANCES || n_consts != C_COUNT || horizon < 1)
        return -1;
    for (int k = 0; k < C_COUNT; ++k) NUM[inst].c[k] = consts[k];
    NUM[inst].in = in;
    NUM[inst].values = values;
    NUM[inst].out = out;
    NUM[inst].u = u;
    NUM[inst].info = info;
    NUM[inst].horizon = horizon;
    NUM[inst].bound = 1;
    return 0;
}

/* feedforward.moving_feedforward, scaled and offset as Controller._feedforward:
 * (R_m / K_T (sign(v) K_coulomb + known)) r_scale + disturbance, the known load torque the
 * sum of effect_use's terms in their order (aero drag c v|v|, the constant load; each a
 * force times the ratio), 0 without terms. */
static double feedforward(const double *c, double v, double r_scale, double dist) {
    double ff = 0.0;
    if (c[C_FF_ON] != 0.0 && !(fabs(v) <= c[C_MOVING])) {
        double known = 0.0;
        if (c[C_HAS_DRAG] != 0.0) known += c[C_AERO] * v * fabs(v) * c[C_RATIO];
        if (c[C_HAS_LOAD] != 0.0) known += c[C_LOAD] * c[C_RATIO];
        ff = c[C_R_M] / c[C_K_T] * (copysign(1.0, v) * c[C_COULOMB] + known);
    }
    return ff * r_scale + dist;
}

/* fallback.limit_command: finite, within du of the previous command and within u_max. */
static double limit_command(double u, double u_prev, double u_max, double du) {
    if (!isfinite(u)) u = 0.0;
    if (!isfinite(u_prev)) u_prev = 0.0;
    double lo = u_prev - du, hi = u_prev + du;
    u = lo > u ? lo : u;
    u = hi < u ? hi : u;
    u = -u_max > u ? -u_max : u;
    return u_max < u ? u_max : u;
}

/* The QP's inputs (condensed.gather's list) into values; 0 when qp.inputs_ok refuses
 * them (their magnitudes summed in order, as Python's sum adds floats). */
static int gather(const double *c, const double *in, double ff, double *values, int64_t n) {
    double v = in[I_V], applied = in[I_APPLIED], moving = c[C_MOVING];
    double ff_now = ff;
    /* delay 0: the acting voltage is the previous one, or the feedforward when held */
    double acting = applied;
    if (fabs(v) <= moving || applied == ff_now) acting = ff;
    values[0] = acting - ff - c[C_K_V] * (v / c[C_RATIO]);
    values[1] = v;
    values[2] = in[I_GAP];
    double u_prev = fabs(v) <= moving ? 0.0 : applied - ff;
    double u_lo = -c[C_U_MAX] - ff, u_hi = in[I_U_HI] - ff;
    double du = c[C_DU];
    double lo0 = u_prev - du, hi0 = u_prev + du; /* qp.first_move_bounds */
    lo0 = u_lo > lo0 ? u_lo : lo0;
    hi0 = u_hi < hi0 ? u_hi : hi0;
    if (lo0 > hi0) {
        double m = u_lo > u_prev ? u_lo : u_prev; /* min(max(u_prev, u_lo), u_hi) */
        lo0 = hi0 = u_hi < m ? u_hi : m;
    }
    double *s = values + NX;
    s[0] = u_prev;
    s[1] = in[I_V_REF];
    s[2] = u_lo;
    s[3] = u_hi;
    s[4] = c[C_V_MAX];
    s[5] = 1.0;
    s[6] = lo0;
    s[7] = hi0;
    for (int64_t k = 0; k < n; ++k) values[NX + N_SCALARS + k] = in[I_LEAD0 + k];
    double sum = 0.0;
    for (int64_t k = 0; k < NX + N_SCALARS + n; ++k) sum += fabs(values[k]);
    return sum < c[C_INPUT_LIMIT];
}

/* One cycle: how's bit 0 the mode (0 follow, 1 cruise), bit 1 lead, bit 3 warm, bit 4 the
 * pair holding the warm start (as truckd_mpc_run; bit 2, one lead speed, is found here).
 * out[O_FF] is the feedforward (V) the command gets (the fallback's when not finished);
 * when the solve is usable (solved or solved inaccurate, finite, within the time budget)
 * out[O_U] is the command (V), out[O_ACTING] the voltage recorded as acting, and
 * out[O_FINISHED] 1.  Returns OSQP's status value, TRUCKD_NUMERICS_BAD_INPUT for inputs
 * refused, or another negative number when the call itself is wrong. */
int64_t truckd_numerics_run(int64_t inst, int64_t how) {
    if (inst < 0 || inst >= TRUCKD_MPC_INSTANCES || !NUM[inst].bound || how < 0 || how > 31)
        return -1;
    const double *c = NUM[inst].c, *in = NUM[inst].in;
    double *out = NUM[inst].out;
    int64_t n = NUM[inst].horizon;
    double v = in[I_V], r_scale = in[I_R_SCALE];
    double ff = feedforward(c, v, r_scale, in[I_DIST]);
    out[O_FF] = ff;
    out[O_FINISHED] = 0.0;
    if (!gather(c, in, ff, NUM[inst].values, n)) return TRUCKD_NUMERICS_BAD_INPUT;
    const double *vl = NUM[inst].values + NX + N_SCALARS;
    int one_speed = 1;
    for (int64_t k = 1; k < n; ++k) one_speed &= vl[k] == vl[0];
    int64_t status = truckd_mpc_run(inst, (how & ~(int64_t)4) | (int64_t)one_speed << 2);
    const double *info = NUM[inst].info;
    if (!((status == 1 || status == 2) && info[3] == 1.0 && !(info[2] > c[C_BUDGET])))
        return status;
    /* Controller._finish: the plan's first move and the feedforward made a command */
    double u_mpc = NUM[inst].u[0], u_max = c[C_U_MAX];
    int at_rest = fabs(v) <= c[C_MOVING]; /* delay 0: at rest when it acts too */
    if (c[C_FF_ON] != 0.0 && at_rest && u_mpc > c[C_START_V]) ff = r_scale * c[C_BREAKAWAY];
    double u = u_mpc + ff;
    if (at_rest && u < 0.0) u = 0.0; /* never drive backwards from rest */
    double wanted = limit_command(u, in[I_APPLIED], u_max, c[C_DU]);
    double a = -u_max > wanted ? -u_max : wanted; /* no current limit: within u_max */
    out[O_ACTING] = u_max < a ? u_max : a;
    out[O_U] = out[O_ACTING]; /* no battery sag, no dead zone: the same clamp */
    out[O_FF] = ff;
    out[O_FINISHED] = 1.0;
    return status;
}

/* The decisions' inputs (truckd_cycle_bind's d_in) and outputs (d_out), see
 * truckd/control/cnumerics.py. */
enum { D_HEADWAY, D_APPLIED, D_V_EXPECTED, D_LIMITED, D_WANTED, D_U_HI, D_DIST, D_R_SCALE };
enum { DO_MODE, DO_LEAD, DO_GAP_REF, DO_DIST };
enum { MODE_FOLLOW, MODE_CRUISE, MODE_STOP };

/* The arrays of the decisions (owned by Python): d_in (8), d_out (4). */
int64_t truckd_cycle_bind(int64_t inst, const double *d_in, double *d_out) {
    if (inst < 0 || inst >= TRUCKD_MPC_INSTANCES || !NUM[inst].bound) return -1;
    NUM[inst].d_in = d_in;
    NUM[inst].d_out = d_out;
    return 0;
}

/* Controller.control from the estimate to the numerics' inputs, when Python holds no
 * standstill (the caller's condition): 0 when a decision is Python's (no valid speed,
 * the hold entered), else 1 with in filled and d_out written.  The same comparisons, in
 * the same order, as controller.py (control) and decisions.py (hold_update's entry, mode_of,
 * disturbance_update) and lead.py (LeadSpeeds.speeds without a forecast or a delay). */
static int decide(const double *c, const double *est, const double *d, double *in,
                  double *d_out, int64_t n) {
    double v = est[0];
    if (!(est[1] != 0.0 && isfinite(v))) return 0; /* the speed fallback: Python's */
    double e_gap = est[2], e_vl = est[3];
    int lead = est[4] != 0.0 && isfinite(e_gap) && isfinite(e_vl);
    double h = d[D_HEADWAY];
    /* never below d_0: a truck moving backwards keeps the standstill gap */
    double gap_ref = lead ? c[C_D0] + h * (v > 0.0 ? v : 0.0) : NAN;
    if (lead && fabs(v) <= c[C_MOVING] && e_vl <= c[C_HOLD_LEAD] &&
        e_gap <= c[C_D0] + c[C_HOLD_GAP])
        return 0; /* the hold begins: Python's */
    int mode;
    double v_ref = c[C_V_SET];
    int near = lead && e_gap - gap_ref < c[C_WINDOW];
    if (near && (e_vl <= c[C_V_SET] || e_gap < gap_ref))
        mode = MODE_FOLLOW;
    else if (lead || c[C_CRUISE_LOST] != 0.0)
        mode = MODE_CRUISE;
    else {
        mode = MODE_STOP;
        v_ref = 0.0;
    }
    /* disturbance_update */
    double dist = d[D_DIST], gain = c[C_DIST_GAIN], expected = d[D_V_EXPECTED];
    double w = d[D_WANTED], u_hi = d[D_U_HI];
    if (gain > 0.0 && d[D_LIMITED] == 0.0 && isfinite(expected) && fabs(v) > c[C_MOVING] &&
        -c[C_U_MAX] + c[C_SATURATED] < w && w < u_hi - c[C_SATURATED]) {
        dist += gain * (expected - v) / c[C_B_V];
        double limit = c[C_DIST_MAX];
        dist = -limit > dist ? -limit : dist; /* min(max(d, -limit), limit) */
        dist = limit < dist ? limit : dist;
    }
    /* LeadSpeeds.speeds: the estimate held, in [0, cap]; 0 without a lead */
    double vl = 0.0;
    if (lead) {
        double cap = mode == MODE_FOLLOW ? c[C_V_SET] : c[C_V_MAX];
        vl = 0.0 > e_vl ? 0.0 : e_vl;
        vl = cap < vl ? cap : vl;
    }
    in[I_V] = v;
    in[I_GAP] = lead ? e_gap - (h - c[C_HEADWAY]) * v : 0.0;
    in[I_APPLIED] = d[D_APPLIED];
    in[I_DIST] = dist;
    in[I_R_SCALE] = d[D_R_SCALE];
    in[I_U_HI] = u_hi;
    in[I_V_REF] = v_ref;
    for (int64_t k = 0; k < n; ++k) in[I_LEAD0 + k] = vl;
    d_out[DO_MODE] = mode;
    d_out[DO_LEAD] = lead;
    d_out[DO_GAP_REF] = gap_ref;
    d_out[DO_DIST] = dist;
    return 1;
}

/* One cycle in one call: the estimator's update (estimator.c), then, when how's bit 5 is
 * set (Python holds no standstill, no forecast), the decisions and truckd_numerics_run
 * (how's bits 3 and 4 as there; the mode and lead bits are decided here).  Returns
 * TRUCKD_CYCLE_ESTIMATED when it stopped after the estimate (not asked further, or a
 * decision that is Python's), else truckd_numerics_run's status; another negative
 * number when the call itself is wrong. */
int64_t truckd_cycle_run(int64_t inst, int64_t how) {
    if (inst < 0 || inst >= TRUCKD_MPC_INSTANCES || how < 0 || how > 63) return -1;
    int64_t r = truckd_estimator_cycle(inst);
    if (r != 0) return r - 10;
    if (!(how & 32)) return TRUCKD_CYCLE_ESTIMATED;
    if (!NUM[inst].bound || NUM[inst].d_in == NULL) return -1;
    const double *est = truckd_estimator_output(inst);
    if (!decide(NUM[inst].c, est, NUM[inst].d_in, NUM[inst].in, NUM[inst].d_out,
                NUM[inst].horizon))
        return TRUCKD_CYCLE_ESTIMATED;
    int64_t mode = NUM[inst].d_out[DO_MODE] == MODE_FOLLOW ? 0 : 1;
    int64_t lead = NUM[inst].d_out[DO_LEAD] != 0.0;
    return truckd_numerics_run(inst, mode | lead << 1 | (how & 24));
}
