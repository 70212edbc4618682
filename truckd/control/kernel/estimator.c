/* The estimator's per-cycle update compiled: own speed from the wheel encoders (the
 * counters' wrap, the glitch rule, the restarts), the lead's gap and speed from the range
 * sensor (gate, outliers, a new target, lead lost), then the estimate.  The same
 * arithmetic, in the same order, as truckd/control/estimator.py (Estimator.update_encoders,
 * update_range, estimate, the Kalman filter _Kf2): the Python estimator is the reference
 * (tests/test_estimator_compiled.py compares both on the recorded replay and on hostile
 * samples).  Python's float remainder (the sign of the divisor) and integer remainder
 * (floor) are written out; a power is libm's pow, as Python's float power calls it.
 *
 * Every constant comes from Python when it binds (truckd/control/cestimator.py); the state
 * lives here, one per MPC instance (the library's instances, instances.h).  Pure
 * numerics: the caller's time comes in with the samples. */
#include <math.h>
#include <stdint.h>

#include "instances.h"
#include "mpc_cycle.h"

/* The constants, in the order truckd/control/cestimator.py's CONSTANTS names them. */
enum {
    E_TICK_LEN,     /* m per tick */
    E_R_TICK,       /* tick_len^2 / 12 (m^2) */
    E_TICKS_MOD,    /* ticks_modulo */
    E_TIME_MOD,     /* sample_time_modulo (s) */
    E_SPEED_ACCEL,  /* speed_accel_std (m/s^2) */
    E_ENC_TIMEOUT,  /* encoder_timeout_s (s) */
    E_SPEED_MAX,    /* speed_max (m/s) */
    E_ACCEL_MAX,    /* accel_max (m/s^2) */
    E_RANGE_MIN,    /* range_min (m) */
    E_RANGE_MAX,    /* range_max (m) */
    E_RANGE_STD,    /* range_noise_std (m) */
    E_LEAD_ACCEL,   /* lead_accel_std (m/s^2) */
    E_GATE_SIGMA,   /* gate_sigma */
    E_REINIT,       /* reinit_count */
    E_LEAD_TIMEOUT, /* lead_timeout_s (s) */
    E_CLOCK_SLACK,  /* CLOCK_SLACK_S (s) */
    E_COUNT
};

enum { MAX_CANDIDATES = 100 }; /* EstimatorConfig.reinit_count's upper bound */
enum { STATUS_NONE, STATUS_TRACKING, STATUS_NO_TARGET, STATUS_TIMEOUT };

typedef struct {
    double x0, x1, p00, p01, p11;
} Kf2;

typedef struct {
    int64_t left, right; /* the counters modulo ticks_modulo */
    double time;
    int left_ok, right_ok;
} Sample;

typedef struct {
    Kf2 kf;
    int has_last, has_behind, suspect;
    Sample last, behind;
    double t_ref, t_last, distance;
    int64_t samples, run, restarts, glitches, valid_from;
} Speed;

typedef struct {
    Kf2 kf;
    int active, status;
    double t_mcu, t_accept;
    double cand_t[MAX_CANDIDATES], cand_d[MAX_CANDIDATES];
    int64_t n_cand, outliers, reinits, samples;
} Lead;

static struct {
    double c[E_COUNT];
    const double *in;
    double *est;
    int64_t size;
    Speed s;
    Lead l;
    int bound;
} EST[TRUCKD_MPC_INSTANCES];

/* Python's float remainder: the result has the divisor's sign (m > 0 here). */
static double py_fmod(double a, double m) {
    double r = fmod(a, m);
    if (r != 0.0) {
        if ((m < 0.0) != (r < 0.0)) r += m;
    } else {
        r = copysign(0.0, m);
    }
    return r;
}

/* wrap_dt */
static double wrap_dt(double new_t, double old_t, double modulo) {
    return py_fmod(new_t - old_t, modulo);
}

/* Python's max(a, b) and min(a, b) of floats (the first unless the second compares). */
static double py_max(double a, double b) { return b > a ? b : a; }

static void kf_predict(Kf2 *k, double dt, double accel_std, double u0) {
    k->x0 += dt * (k->x1 + u0);
    double q = accel_std * accel_std;
    double p00 = k->p00 + dt * (2.0 * k->p01 + dt * k->p11) + q * pow(dt, 4.0) / 4.0;
    double p01 = k->p01 + dt * k->p11 + q * pow(dt, 3.0) / 2.0;
    k->p11 = k->p11 + q * dt * dt;
    k->p00 = p00;
    k->p01 = p01;
}

static void kf_update(Kf2 *k, double z, double r) {
    double y = z - k->x0, s = k->p00 + r;
    double k0 = k->p00 / s, k1 = k->p01 / s;
    k->x0 += k0 * y;
    k->x1 += k1 * y;
    double p00 = (1.0 - k0) * k->p00;
    double p01 = (1.0 - k0) * k->p01;
    double p11 = k->p11 - k1 * k->p01;
    k->p00 = p00;
    k->p01 = p01;
    k->p11 = p11;
}

static void reset(Speed *s, Lead *l) {
    Kf2 start = {0.0, 0.0, 1.0, 0.0, 1.0};
    s->kf = start;
    s->has_last = s->has_behind = s->suspect = 0;
    s->t_ref = s->t_last = -INFINITY;
    s->distance = 0.0;
    s->samples = s->run = s->restarts = s->glitches = 0;
    s->valid_from = 2;
    l->kf = start;
    l->active = 0;
    l->status = STATUS_NONE;
    l->t_mcu = 0.0;
    l->t_accept = -INFINITY;
    l->n_cand = l->outliers = l->reinits = l->samples = 0;
}

int64_t truckd_estimator_consts(void) { return E_COUNT; }

/* The constants (copied), the arrays each cycle reads (in, size values: the caller's
 * time, the numbers of encoder and range samples, then the encoder samples of 5 values
 * each, [left, right] counters modulo ticks_modulo, sample time, left ok, right ok, then
 * the range samples of 2, [distance or NaN, sample time]) and writes (est, the 16 fields
 * of truckd/control/cestimator.py's FIELDS); reset (1): the state starts again.
 * 0: done. */
int64_t truckd_estimator_bind(int64_t inst, const double *consts, int64_t n_consts,
                              const double *in, double *est, int64_t size, int64_t reset_) {
    if (inst < 0 || inst >= TRUCKD_MPC_INSTANCES || n_consts != E_COUNT || size < 3)
        return -1;
    if (!(consts[E_REINIT] >= 1.0 && consts[E_REINIT] <= MAX_CANDIDATES)) return -2;
    if (!(consts[E_TICKS_MOD] >= 2.0 && consts[E_TICKS_MOD] <= 4294967296.0)) return -3;
    for (int k = 0; k < E_COUNT; ++k) EST[inst].c[k] = consts[k];
    EST[inst].in = in;
    EST[inst].est = est;
    EST[inst].size = size;
    if (reset_) reset(&EST[inst].s, &EST[inst].l);
    EST[inst].bound = 1;
    return 0;
}

/* Estimator._restart */
static void restart(Speed *st, const Sample *s, double t) {
    st->last = *s;
    st->has_last = 1;
    st->t_ref = t;
    st->run = 1;
    st->has_behind = 0;
    st->suspect = 0;
    st->valid_from = 3;
    st->restarts += 1;
}

/* Estimator._speed_room */
static double speed_room(const double *c, const Speed *st, double dt) {
    double p11 = st->kf.p11;
    double sd = sqrt(0.0 > p11 ? 0.0 : p11);
    return (c[E_ACCEL_MAX] * dt + 4.0 * sd) * dt + 2.0 * c[E_TICK_LEN];
}

/* The healthy wheels' difference (wrap_delta: Python's floor remainder) */
static int64_t wrap_ticks(int64_t a, int64_t b, int64_t m) {
    int64_t half = m / 2, r = (a - b + half) % m;
    return (r < 0 ? r + m : r) - half;
}

/* Estimator.update_encoders, branch for branch. */
static void update_encoders(const double *c, Speed *st, double t, const Sample *s) {
    if (!(isfinite(t) && isfinite(s->time))) return;
    st->samples += 1;
    if (!st->has_last) {
        st->last = *s;
        st->has_last = 1;
        st->t_ref = t;
        st->run = 1;
        return;
    }
    double modulo = c[E_TIME_MOD];
    double dt = wrap_dt(s->time, st->last.time, modulo);
    if (dt <= 0.0) return; /* the same sample again */
    if (dt > 0.5 * modulo) { /* behind the last one */
        Sample prev = st->behind;
        int had = st->has_behind;
        st->behind = *s;
        st->has_behind = 1;
        if (!had) return; /* out of order: dropped */
        dt = wrap_dt(s->time, prev.time, modulo);
        if (!(0.0 < dt && dt < 0.5 * modulo)) return;
        restart(st, &prev, t); /* the firmware's clock restarted */
    } else if (dt > (t - st->t_ref) + c[E_CLOCK_SLACK]) {
        restart(st, s, t); /* the firmware's clock ran ahead of the caller's */
        return;
    }
    st->has_behind = 0;
    int64_t m = (int64_t)c[E_TICKS_MOD];
    const Sample *last = &st->last;
    int64_t total = 0, wheels = 0;
    if (s->left_ok && last->left_ok) {
        total = wrap_ticks(s->left, last->left, m);
        wheels = 1;
    }
    if (s->right_ok && last->right_ok) {
        total += wrap_ticks(s->right, last->right, m);
        wheels += 1;
    }
    if (!wheels) {
        st->last = *s;
        st->t_ref = t;
        st->suspect = 0;
        return; /* no healthy wheel: the speed goes stale */
    }
    double tick_len = c[E_TICK_LEN];
    double step = tick_len * (double)total / (double)wheels;
    if (fabs(step) > c[E_SPEED_MAX] * dt + 2.0 * tick_len ||
        (st->run >= 2 && fabs(step - st->kf.x1 * dt) > speed_room(c, st, dt))) {
        if (st->run >= 2 && !st->suspect) {
            st->suspect = 1; /* dropped: the next sample tells a glitch from a jump */
            return;
        }
        restart(st, s, t);
        return;
    }
    if (st->suspect) {
        st->suspect = 0;
        st->glitches += 1;
    }
    st->last = *s;
    st->t_ref = t;
    st->distance += step;
    st->run += 1;
    double r_tick = c[E_R_TICK];
    if (st->run == 2) {
        double var_v = 2.0 * r_tick / (dt * dt);
        Kf2 start = {st->distance, step / dt, r_tick, 0.0, var_v};
        st->kf = start;
    } else {
        kf_predict(&st->kf, dt, c[E_SPEED_ACCEL], 0.0);
        kf_update(&st->kf, st->distance, r_tick / (double)wheels);
    }
    st->t_last = t;
}

/* Estimator._predict_lead */
static void predict_lead(const double *c, Lead *ld, double t_mcu, double v_own) {
    double modulo = c[E_TIME_MOD];
    double dt = wrap_dt(t_mcu, ld->t_mcu, modulo);
    if (0.0 < dt && dt < 0.5 * modulo) {
        kf_predict(&ld->kf, dt, c[E_LEAD_ACCEL], -v_own);
        ld->kf.x1 = py_max(ld->kf.x1, 0.0);
        ld->t_mcu = t_mcu;
    } else if (dt > 0.0) {
        ld->t_mcu = t_mcu;
    }
}

/* Estimator._start */
static void start(const double *c, Lead *ld, double t, double t_mcu, double d, double v_own) {
    Kf2 k = {d, v_own, pow(c[E_RANGE_STD], 2.0), 0.0, 1.0};
    ld->kf = k;
    ld->active = 1;
    ld->t_mcu = t_mcu;
    ld->t_accept = t;
    ld->status = STATUS_TRACKING;
    ld->n_cand = 0;
}

/* Estimator._consider_new_target */
static void consider(const double *c, Lead *ld, double t, double t_mcu, double d, double v_own) {
    double tol = 3.0 * c[E_RANGE_STD] + 0.05;
    if (ld->n_cand > 0) {
        double t_prev = ld->cand_t[ld->n_cand - 1], d_prev = ld->cand_d[ld->n_cand - 1];
        double dt = wrap_dt(t_mcu, t_prev, c[E_TIME_MOD]);
        if (fabs(d - d_prev) > tol + 3.0 * dt) ld->n_cand = 0;
    }
    ld->cand_t[ld->n_cand] = t_mcu;
    ld->cand_d[ld->n_cand] = d;
    ld->n_cand += 1;
    if ((double)ld->n_cand >= c[E_REINIT]) {
        double t0 = ld->cand_t[0], d0 = ld->cand_d[0];
        double t1 = ld->cand_t[ld->n_cand - 1], d1 = ld->cand_d[ld->n_cand - 1];
        double span = wrap_dt(t1, t0, c[E_TIME_MOD]);
        double closing = span > 0.0 ? (d1 - d0) / span : 0.0;
        start(c, ld, t, t_mcu, d1, v_own + closing);
        ld->kf.p11 = 0.25; /* 0.5 ** 2 */
        ld->reinits += 1;
    }
}

/* Estimator.update_range (d NaN: no valid target, as None) */
static void update_range(const double *c, Lead *ld, double t, double d, double t_mcu,
                         double v_own) {
    if (!(isfinite(t) && isfinite(t_mcu) && isfinite(v_own))) return;
    ld->samples += 1;
    double range_min = c[E_RANGE_MIN];
    if (0.0 <= d && d < range_min) d = range_min;
    if (!isfinite(d) || !(range_min <= d && d <= c[E_RANGE_MAX])) {
        if (ld->active) predict_lead(c, ld, t_mcu, v_own);
        ld->status = STATUS_NO_TARGET;
        ld->n_cand = 0;
        return;
    }
    double var_r = pow(c[E_RANGE_STD], 2.0);
    if (!ld->active) {
        start(c, ld, t, t_mcu, d, v_own);
        return;
    }
    predict_lead(c, ld, t_mcu, v_own);
    double y = d - ld->kf.x0, s = ld->kf.p00 + var_r;
    if (y * y <= pow(c[E_GATE_SIGMA], 2.0) * s) {
        kf_update(&ld->kf, d, var_r);
        ld->t_accept = t;
        ld->status = STATUS_TRACKING;
        ld->n_cand = 0;
        return;
    }
    ld->outliers += 1;
    consider(c, ld, t, t_mcu, d, v_own);
}

/* Estimator.estimate into est (the order of truckd/control/cestimator.py's FIELDS) */
static void estimate(const double *c, Speed *st, Lead *ld, double t, double *est) {
    double v = st->kf.x1;
    int speed_ok = st->run >= st->valid_from && (t - st->t_last) <= c[E_ENC_TIMEOUT];
    int lost = (t - ld->t_accept) > c[E_LEAD_TIMEOUT];
    int valid = ld->active && !lost;
    if (ld->active && lost) ld->active = 0;
    int status = ld->status;
    if (!valid && status == STATUS_TRACKING) status = STATUS_TIMEOUT;
    double gap = NAN, v_lead = NAN, std = NAN, v_lead_std = NAN;
    if (valid) {
        gap = ld->kf.x0;
        v_lead = ld->kf.x1;
        if (st->has_last) {
            double dt = wrap_dt(st->last.time, ld->t_mcu, c[E_TIME_MOD]);
            if (dt < 0.5) gap += dt * (v_lead - v);
        }
        double p00 = ld->kf.p00, p11 = ld->kf.p11;
        std = sqrt(0.0 > p00 ? 0.0 : p00);
        v_lead_std = sqrt(0.0 > p11 ? 0.0 : p11);
    }
    est[0] = v;
    est[1] = speed_ok;
    est[2] = gap;
    est[3] = v_lead;
    est[4] = valid;
    est[5] = status;
    est[6] = std;
    est[7] = (double)ld->outliers;
    est[8] = (double)ld->reinits;
    est[9] = (double)st->samples;
    est[10] = (double)ld->samples;
    est[11] = (double)st->restarts;
    est[12] = (double)st->glitches;
    est[13] = t - st->t_last;
    est[14] = v_lead_std;
    est[15] = st->distance;
}

int64_t truckd_estimator_cycle(int64_t inst) {
    if (inst < 0 || inst >= TRUCKD_MPC_INSTANCES || !EST[inst].bound) return -1;
    const double *c = EST[inst].c, *in = EST[inst].in;
    double t = in[0], n_enc = in[1], n_rng = in[2];
    double needed = 3.0 + 5.0 * n_enc + 2.0 * n_rng;
    if (!(n_enc >= 0.0 && n_rng >= 0.0 && needed <= (double)EST[inst].size)) return -2;
    Speed *st = &EST[inst].s;
    Lead *ld = &EST[inst].l;
    const double *e = in + 3;
    for (int64_t k = 0; k < (int64_t)n_enc; ++k, e += 5) {
        Sample s = {(int64_t)e[0], (int64_t)e[1], e[2], e[3] != 0.0, e[4] != 0.0};
        update_encoders(c, st, t, &s);
    }
    const double *r = e; /* the range samples follow the encoder samples */
    for (int64_t k = 0; k < (int64_t)n_rng; ++k, r += 2)
        update_range(c, ld, t, r[0], r[1], st->kf.x1); /* v_own: Estimator.speed's */
    estimate(c, st, ld, t, EST[inst].est);
    return 0;
}

const double *truckd_estimator_output(int64_t inst) { return EST[inst].est; }
