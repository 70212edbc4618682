/* The free-run loop of truckd/ident/freerun.py (function run) in C, for the fitting loop.
 *
 * Same arithmetic, same order, as the Python reference: a first-order drivetrain with
 * Coulomb friction and stiction, each sub-interval solved exactly (truckd/ident/freerun.py
 * explains the model).  The Python loop stays the reference and the fallback; tests
 * check both give the same speeds (tests/test_ident_kernel.py).  Pure computation.
 */
#include <math.h>
#include <stdint.h>

/* The kernel's version: raise it with every change of the loops' arithmetic or of the
 * functions' arguments, together with ABI in truckd/ident/ckernel.py, which refuses a
 * library of another version (a stale build) and runs the Python loop instead. */
#define TRUCKD_FASTRUN_ABI 5

int truckd_fastrun_abi(void);
int truckd_fastrun_abi(void)
{
    return TRUCKD_FASTRUN_ABI;
}

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

static void phi(double b, double h, double *e, double *p1, double *p2)
{
    double bh = b * h;
    if (bh < 1e-5) {
        *p1 = h * (1.0 - 0.5 * bh + bh * bh / 6.0);
        *p2 = h * h * (0.5 - bh / 6.0 + bh * bh / 24.0);
        *e = 1.0 - bh + 0.5 * bh * bh;
        return;
    }
    double em1 = -expm1(-bh);
    *p1 = em1 / b;
    *e = 1.0 - em1;
    *p2 = (h - *p1) / b;
}

/* The breakaway threshold (per unit inertia) and the band of thresholds that would have
 * taken every stick-or-break decision of a run the same way: a run stuck where
 * |net| <= sigma, so any threshold >= stuck keeps those; it broke away where |net| > sigma,
 * so any threshold < moved keeps those.  A threshold in [stuck, moved) gives the same run. */
struct stick {
    double sigma;
    double stuck;
    double moved;
};

/* One segment of length h: end speed, *dist = integral of speed. */
static double segment(double w, double a, double b, double c, struct stick *st, double d,
                      double h, double lag, double *dist)
{
    double extra = 0.0;
    *dist = 0.0;
    for (int it = 0; it < 4; ++it) {
        double s, g, e, p1, p2, w1;
        if (h <= 0.0) {
            break;
        }
        if (w == 0.0) {
            double net = a - d + extra;
            double mag = fabs(net);
            extra = 0.0;
            if (mag <= st->sigma) {
                st->stuck = fmax(st->stuck, mag);
                return 0.0;
            }
            st->moved = fmin(st->moved, mag);
            s = net > 0.0 ? 1.0 : -1.0;
        } else {
            s = w > 0.0 ? 1.0 : -1.0;
        }
        g = a - s * c - d;
        phi(b, h, &e, &p1, &p2);
        w1 = w * e + g * p1;
        if (w1 * s > 0.0) {
            *dist += w * p1 + g * p2;
            return w1;
        }
        if (w == 0.0 || g * s >= 0.0) {
            return 0.0;
        }
        {
            double x = -b * w / g;
            double tz = b * h > 1e-9 ? log1p(x) / b : -w / g;
            double e2, q1, q2;
            tz = fmin(fmax(tz, 0.0), h);
            phi(b, tz, &e2, &q1, &q2);
            *dist += w * q1 + g * q2;
            h -= tz;
            w = 0.0;
            extra = b * g * lag;
        }
    }
    return w;
}

/* Position-dependent load per unit inertia at motor angle x (freerun.Terrain): ter =
 * {per_newton, ratio, x0, amplitude, wavelength, phase, hill_force, hill_start,
 * hill_length}, as truckd.model.effects.terrain_force. */
static double terrain(const double *ter, double angle)
{
    double x = ter[2] + angle * ter[1];
    double force = 0.0;
    if (ter[3] != 0.0) {
        double ph = 2.0 * M_PI * x / ter[4] + ter[5];
        force += ter[3] * sin(ph);
    }
    if (ter[6] != 0.0 && ter[7] <= x && x < ter[7] + ter[8]) {
        force += ter[6];
    }
    return ter[0] * force;
}

/* Sliding friction above Coulomb per unit inertia at speed w (freerun.Stribeck): stb =
 * {per_nm, amplitude, ratio, speed}, as truckd.model.effects.stribeck_torque. */
static double stribeck(const double *stb, double w)
{
    double z = w * stb[2] / stb[3];
    return stb[0] * (stb[1] * exp(-z * z));
}

/* freerun._time_to: when the speed, sliding from w under dw/dt = a - b w - s c - d,
 * reaches target of the same sign; returns 0 when it does not (*t unset). */
static int time_to(double w, double target, double a, double b, double c, double d, double *t)
{
    double s, g, ratio, tt;
    if (w == 0.0 || w * target <= 0.0) {
        return 0;
    }
    s = w > 0.0 ? 1.0 : -1.0;
    g = a - s * c - d;
    if (b * fabs(target - w) < 1e-9 * fmax(fabs(g), 1e-300)) {
        tt = g != 0.0 ? (target - w) / g : -1.0;
        if (tt >= 0.0) {
            *t = tt;
            return 1;
        }
        return 0;
    }
    ratio = (target - g / b) / (w - g / b);
    if (!(ratio > 0.0)) {
        return 0;
    }
    tt = -log(ratio) / b;
    if (tt >= 0.0) {
        *t = tt;
        return 1;
    }
    return 0;
}

/* freerun._limited: a sub-interval that starts with the current limit binding (a_max the
 * largest drive); returns 0 when the limit does not bind at its start. */
static int limited(double w, double a, double b, double b_mech, double a_max, double c,
                   struct stick *st, double d, double h, double lag, double *w_out,
                   double *dist)
{
    double b_emf = b - b_mech;
    double drive = a - b_emf * w;
    double s_l, a_l, w_end, dx, w_star, t_rel, lo, hi, d1, d2, w1;
    if (fabs(drive) <= a_max) {
        return 0;
    }
    s_l = drive > 0.0 ? 1.0 : -1.0;
    a_l = s_l * a_max;
    w_end = segment(w, a_l, b_mech, c, st, d, h, lag, &dx);
    if (b_emf <= 0.0 || fabs(a - b_emf * w_end) >= a_max) {
        *w_out = w_end;
        *dist = dx;
        return 1;
    }
    w_star = (a - a_l) / b_emf;
    if (time_to(w, w_star, a_l, b_mech, c, d, &t_rel) && 0.0 <= t_rel && t_rel <= h) {
        w1 = segment(w, a_l, b_mech, c, st, d, t_rel, lag, &d1);
        *w_out = segment(w1, a, b, c, st, d, h - t_rel, lag, &d2);
        *dist = d1 + d2;
        return 1;
    }
    lo = 0.0;
    hi = h;
    for (int it = 0; it < 40; ++it) {
        double mid = 0.5 * (lo + hi), dm;
        double wm = segment(w, a_l, b_mech, c, st, d, mid, lag, &dm);
        if ((wm - w_star) * s_l < 0.0) {
            lo = mid;
        } else {
            hi = mid;
        }
        if (hi - lo <= 1e-9 * h) {
            break;
        }
    }
    w1 = segment(w, a_l, b_mech, c, st, d, hi, lag, &d1);
    *w_out = segment(w1, a, b, c, st, d, h - hi, lag, &d2);
    *dist = d1 + d2;
    return 1;
}

/* The backlash gap (freerun.GapRun with truckd.model.effects.gap_opens and
 * gap_free_motion): gp = {K_T, K_v, J_S, K_stiction, R_m, rotor_inertia_fraction,
 * backlash, cap (largest motor torque), per (N m per unit of the run's coefficients),
 * v_idle, step (longest free-motion step, s), current limit (A, 0 = none)}; volts, r per
 * command; state = {side, angle, rotor}. */
static int gap_opens(const double *gp, const double *state, double omega, double volts,
                     double r, double coulomb, double load, double viscous)
{
    double motor = gp[0] * (volts - gp[1] * omega) / r;
    double resist, j_r, contact;
    motor = fmin(fmax(motor, -gp[7]), gp[7]);
    if (omega != 0.0) {
        resist = copysign(coulomb, omega) + load + viscous * omega;
    } else {
        resist = load + fmin(fmax(motor - load, -gp[3]), gp[3]);
    }
    j_r = gp[5] * gp[2];
    contact = ((gp[2] - j_r) * motor + j_r * resist) / gp[2];
    return contact * state[0] < 0.0;
}

static double gap_free_motion(const double *gp, double *state, double w_load, double volts,
                              double r, double coulomb, double load, double viscous, double h,
                              double *travelled_out, double *used_out)
{
    double j_r = gp[5] * gp[2];
    double j_l = gp[2] - j_r;
    double half = 0.5 * gp[6];
    double w_inf = volts / gp[1];
    double rate = gp[0] * gp[1] / (r * j_r);
    double used = 0.0, travelled = 0.0;
    while (used < h) {
        double dt = fmin(gp[10], h - used);
        double e = exp(-rate * dt);
        double wr1 = w_inf + (state[2] - w_inf) * e;
        double ang_r = w_inf * dt + (state[2] - w_inf) * (1.0 - e) / rate;
        double wl1, ang_l, angle, moving;
        if (w_load != 0.0) {
            double sg = w_load > 0.0 ? 1.0 : -1.0;
            double dec = (sg * coulomb + load + viscous * w_load) / j_l;
            wl1 = w_load - dec * dt;
            if (wl1 * sg <= 0.0 && dec * sg > 0.0) {
                double t_stop = w_load / dec;
                ang_l = 0.5 * w_load * t_stop;
                wl1 = 0.0;
            } else {
                ang_l = 0.5 * (w_load + wl1) * dt;
            }
        } else if (fabs(load) > gp[3]) {
            double acc = -(load - copysign(coulomb, load)) / j_l;
            wl1 = acc * dt;
            ang_l = 0.5 * wl1 * dt;
        } else {
            wl1 = 0.0;
            ang_l = 0.0;
        }
        angle = state[1] + ang_r - ang_l;
        moving = angle - state[1];
        if ((angle >= half && moving > 0.0) || (angle <= -half && moving < 0.0)) {
            double side = moving > 0.0 ? 1.0 : -1.0;
            double frac = (side * half - state[1]) / moving;
            double w_r, w_l, w;
            frac = fmin(fmax(frac, 0.0), 1.0);
            w_r = state[2] + frac * (wr1 - state[2]);
            w_l = w_load + frac * (wl1 - w_load);
            w = (j_r * w_r + j_l * w_l) / gp[2];
            state[0] = side;
            state[1] = side * half;
            state[2] = w;
            *travelled_out = travelled + frac * ang_l;
            *used_out = used + frac * dt;
            return w;
        }
        state[1] = angle;
        state[2] = wr1;
        w_load = wl1;
        travelled += ang_l;
        used += dt;
    }
    *travelled_out = travelled;
    *used_out = used;
    return w_load;
}

/* Rigid motion over dur seconds (no gap, no current limit): the closed form while the
 * speed keeps its sign (and b dur is not negligible), else segment(); the distance in *dx. */
static double roll(double w, double a, double b, double c, struct stick *st, double d,
                   double dur, double lag, double *dx)
{
    double bh = b * dur;
    if (w != 0.0 && bh >= 1e-5) {
        double s = w > 0.0 ? 1.0 : -1.0;
        double g = a - s * c - d;
        double em1 = -expm1(-bh);
        double p1 = em1 / b;
        double w1 = w * (1.0 - em1) + g * p1;
        if (w1 * s > 0.0) {
            *dx = w * p1 + g * (dur - p1) / b;
            return w1;
        }
    }
    return segment(w, a, b, c, st, d, dur, lag, dx);
}

/* A resistance drift stepped beside the speed (heating.heat_arrays builds the inputs): the winding's rise at
 * each sample from the current the run itself draws (the rotor's back-EMF: across a
 * backlash gap the rotor's speed, not the load's), each command's resistance from the
 * rise when it was issued, and from it the command's a, b and scale (written on first use;
 * scale NaN until then).  hp: R_m, tempco, drift (K/W), tau (s), rise0 (K), L_m, J_S, K_T,
 * K_v, viscous, kappa (the cold electrical correction), current limit (0: none), v_pre,
 * the history commands' extra resistance.  Per command: volts, sag (the battery's
 * resistance), kk (the sample whose rise it sees; -1: issued before the log), r (written;
 * NaN until known).  Per sample: at and prev (the active command and the one before it,
 * -1: none), since (minus the time since the active command acted), h (the steps, one
 * fewer), rise (written). */
struct heat {
    const double *hp, *volts, *sag, *since, *h;
    const int64_t *kk, *at, *prev;
    double *r, *rise, *a, *b, *scale;
    int64_t done; /* the last sample whose rise is known */
    double i_prev; /* the current at that sample */
};

static double heat_r(struct heat *ht, int64_t k)
{
    if (isnan(ht->r[k])) {
        const double *hp = ht->hp;
        double extra = hp[13];
        if (ht->kk[k] >= 0) {
            int64_t s = ht->kk[k] <= ht->done ? ht->kk[k] : ht->done;
            extra = hp[0] * (1.0 + hp[1] * ht->rise[s]) - hp[0];
        }
        ht->r[k] = hp[0] + ht->sag[k] + extra;
    }
    return ht->r[k];
}

/* fastsim.electrical_correction and fastsim._prepare's a, b and scale of command k */
static void heat_coefficients(struct heat *ht, int64_t k)
{
    const double *hp = ht->hp;
    double r = heat_r(ht, k), el = hp[5], j = hp[6], kt = hp[7], kv = hp[8], visc = hp[9];
    double tr = -(r / el + visc / j);
    double det = (r * visc + kv * kt) / (el * j);
    double disc = sqrt(fmax(tr * tr / 4.0 - det, 0.0));
    double lam_s = tr / 2.0 + disc;
    double beta = (kt * kv / r + visc) / j;
    double kc = -lam_s / beta;
    ht->a[k] = kc * kt / j * ht->volts[k] / r;
    ht->b[k] = kc * (kt * kv / r + visc) / j;
    ht->scale[k] = kc / hp[10];
}

/* fastsim._sample_currents at sample s, the rotor at w */
static double heat_current(struct heat *ht, int64_t s, double w)
{
    const double *hp = ht->hp;
    int64_t at = ht->at[s], pv = ht->prev[s];
    double v_at = at >= 0 ? ht->volts[at] : hp[12];
    double v_old = pv >= 0 ? ht->volts[pv] : hp[12];
    double r_at = at >= 0 ? heat_r(ht, at) : hp[0];
    double r_old = pv >= 0 ? heat_r(ht, pv) : hp[0];
    double settle = exp(ht->since[s] * r_at / hp[5]);
    double emf = hp[8] * w;
    double cur = (v_at - emf) / r_at;
    double old = (v_old - emf) / r_old;
    cur = cur + (old - cur) * settle;
    if (hp[11] != 0.0) {
        cur = fmin(fmax(cur, -hp[11]), hp[11]);
    }
    return cur;
}

/* the rise at samples done + 1 .. s (the rotor at w there), as truckd_winding_rises */
static void heat_samples(struct heat *ht, int64_t s, double w)
{
    const double *hp = ht->hp;
    for (int64_t q = ht->done + 1; q <= s; ++q) {
        double i = heat_current(ht, q, w);
        double before = ht->rise[q - 1];
        double r = hp[0] * (1.0 + hp[1] * before);
        double power = 0.5 * (ht->i_prev * ht->i_prev + i * i) * r;
        double e = exp(-ht->h[q - 1] / hp[3]);
        ht->rise[q] = before * e + hp[2] * power * (1.0 - e);
        ht->done = q;
        ht->i_prev = i;
    }
}

/* See freerun.run.  scale may be NULL (1 everywhere), ter NULL (no terrain), stb NULL (no
 * Stribeck friction), lim NULL (no current limit; else {a_max, b_mech}), gp NULL (no
 * backlash; else as gap_opens, with gvolts, gr per command (hp set: the heated resistance
 * of struct heat instead), gstate the gap's state, which
 * the run changes, and rotor_out the rotor speed at each sample), band NULL or two
 * doubles that receive the run's band of breakaway thresholds (struct stick): with scale
 * and stb NULL the threshold is ksigma throughout, and any ksigma in [band[0], band[1])
 * gives this run exactly.  hp NULL: no resistance drift; else struct heat's arrays, a, b
 * and scale written as each command first acts (m_cmd commands).  Returns 0. */
int truckd_fastrun(double *a, double *b, double a_idle, double b_idle, double kc,
                   double ksigma, double kd, double kdrag, double *scale, double lag,
                   const double *dt, const int64_t *cmd, const int64_t *sample_end, int64_t m,
                   int64_t n, double w0, double sensor_lag, double *out, double *raw, double *pos,
                   const double *ter, const double *stb, const double *lim, const double *gp,
                   const double *gvolts, const double *gr, double *gstate, double *rotor_out,
                   double *band, const double *hp, int64_t m_cmd, const double *hvolts,
                   const double *hsag, const int64_t *hkk, const int64_t *hat,
                   const int64_t *hprev, const double *hsince, const double *hh, double *hr,
                   double *hrise)
{
    double w = w0, v_lag = w0, x = 0.0, x_step0 = 0.0, h_step = 0.0;
    double c = kc, d = kd, drag = kdrag;
    struct stick st = {ksigma, -INFINITY, INFINITY};
    double last_h = -1.0, last_alpha = 0.0;
    if (band != 0) {
        band[0] = -INFINITY;
        band[1] = INFINITY;
    }
    if (n < 1) {
        return 0;
    }
    out[0] = raw[0] = w0;
    pos[0] = 0.0;
    struct heat heat_run = {hp, hvolts, hsag, hsince, hh, hkk, hat, hprev, hr, hrise, a, b,
                            scale, 0, 0.0};
    struct heat *ht = hp != 0 ? &heat_run : 0;
    if (ht != 0) {
        hrise[0] = hp[4];
        ht->i_prev = heat_current(ht, 0, w0);
    }
    for (int64_t j = 0; j < m; ++j) {
        double h = dt[j], aa, bb, b_eff, d_eff;
        int64_t k = cmd[j], se = sample_end[j];
        double f = 1.0;
        if (k >= 0) {
            if (ht != 0 && isnan(scale[k])) {
                heat_coefficients(ht, k);
            }
            aa = a[k];
            bb = b[k];
            if (scale != 0) {
                f = scale[k];
                c = kc * f;
                st.sigma = ksigma * f;
                d = kd * f;
                drag = kdrag * f;
            }
        } else {
            aa = a_idle;
            bb = b_idle;
        }
        if (ter != 0) {
            d = (kd + terrain(ter, x)) * f;
        }
        if (stb != 0) {
            /* Breakaway takes at least the sliding friction at zero speed; the sliding
             * friction at the speed halfway through the sub-interval (midpoint). */
            st.sigma = fmax(ksigma, kc + stribeck(stb, 0.0)) * f;
            c = (kc + stribeck(stb, w)) * f;
            if (h > 0.0) {
                double dh;
                double w_half = segment(w, aa, bb, c, &st, d, 0.5 * h, lag, &dh);
                c = (kc + stribeck(stb, w != 0.0 ? 0.5 * (w + w_half) : w_half)) * f;
            }
        }
        if (drag != 0.0) {
            double aw = fabs(w);
            b_eff = bb + 2.0 * drag * aw;
            d_eff = d - drag * w * aw;
        } else {
            b_eff = bb;
            d_eff = d;
        }
        if (lim != 0 || gp != 0) {
            /* the gap (freerun.GapRun.step), then freerun._rigid */
            double wl, dl, rigid = h;
            double b_mech = lim != 0 ? lim[1] : 0.0;
            if (gp != 0) {
                double b_m = b_mech * f + (b_eff - bb);
                double volts = k >= 0 ? gvolts[k] : gp[9];
                double r = k < 0 ? gp[4] : ht != 0 ? heat_r(ht, k) : gr[k];
                double coulomb = c / f * gp[8], load = d_eff / f * gp[8];
                double viscous = b_m / f * gp[8];
                int moves = 1;
                if (gp[11] != 0.0) {
                    /* effects.current_limited at the load's speed, as the plant */
                    double emf = gp[1] * w, room = r * gp[11];
                    volts = fmin(fmax(volts, emf - room), emf + room);
                }
                if (gstate[0] != 0.0) {
                    if (!gap_opens(gp, gstate, w, volts, r, coulomb, load, viscous)) {
                        moves = 0;
                    } else {
                        gstate[0] = 0.0;
                        gstate[2] = w;
                    }
                }
                if (moves) {
                    double used;
                    w = gap_free_motion(gp, gstate, w, volts, r, coulomb, load, viscous, h, &dl,
                                        &used);
                    x += dl;
                    rigid = h - used;
                }
            }
            if (rigid > 0.0) {
                double b_m = b_mech * f + (b_eff - bb);
                if (lim != 0 &&
                    limited(w, aa, b_eff, b_m, lim[0], c, &st, d_eff, rigid, lag, &wl, &dl)) {
                    w = wl;
                    x += dl;
                } else {
                    w = roll(w, aa, b_eff, c, &st, d_eff, rigid, lag, &dl);
                    x += dl;
                }
            }
        } else {
            double dx;
            w = roll(w, aa, b_eff, c, &st, d_eff, h, lag, &dx);
            x += dx;
        }
        h_step += h;
        if (gp != 0 && se >= 0 && se < n) {
            rotor_out[se] = gstate[0] == 0.0 ? gstate[2] : w;
        }
        if (ht != 0 && se > ht->done && se < n) {
            heat_samples(ht, se, gp != 0 ? rotor_out[se] : w); /* the rotor's back-EMF */
        }
        if (se >= 0 && se < n) {
            raw[se] = w;
            pos[se] = x;
            if (sensor_lag > 0.0) {
                if (h_step != last_h) {
                    last_alpha = 1.0 - exp(-h_step / sensor_lag);
                    last_h = h_step;
                }
                v_lag += last_alpha * ((x - x_step0) / h_step - v_lag);
                out[se] = v_lag;
            } else {
                out[se] = w;
            }
            x_step0 = x;
            h_step = 0.0;
        }
    }
    if (band != 0) {
        band[0] = st.stuck;
        band[1] = st.moved;
    }
    if (ht != 0) { /* commands that never acted: from the last rise known */
        heat_samples(ht, n - 1, gp != 0 && gstate[0] == 0.0 ? gstate[2] : w);
        for (int64_t k = 0; k < m_cmd; ++k) {
            if (isnan(scale[k])) {
                heat_coefficients(ht, k);
            }
        }
    }
    return 0;
}

/* fastsim.winding_rises: the winding's temperature rise at each of n samples from rise0,
 * sq the squared currents, h the n - 1 time steps (s); r_m (ohm), tempco (1/K), drift
 * (K/W), tau (s) as truckd.model.effects.winding_resistance and winding_rise_step.
 * Returns 0. */
int truckd_winding_rises(const double *h, const double *sq, int64_t n, double rise0, double r_m,
                         double tempco, double drift, double tau, double *out)
{
    double rise = rise0;
    if (n < 1) {
        return 0;
    }
    out[0] = rise;
    for (int64_t k = 0; k + 1 < n; ++k) {
        double r = r_m * (1.0 + tempco * rise);
        double power = 0.5 * (sq[k] + sq[k + 1]) * r;
        double e = exp(-h[k] / tau);
        rise = rise * e + drift * power * (1.0 - e);
        out[k + 1] = rise;
    }
    return 0;
}

/* scipy.signal.lfilter([0, b1], [1, a1], x, axis=0) of the rows x cols row-major x into y,
 * in the arithmetic of scipy's direct form II transposed (y = z + 0 x; z = x b1 - y a1 per
 * column, z from 0): terrain._filtered's first-order filter without importing scipy.signal.
 * Returns 0. */
int truckd_first_order(const double *x, int64_t rows, int64_t cols, double b1, double a1,
                       double *z, double *y)
{
    for (int64_t c = 0; c < cols; ++c) {
        z[c] = 0.0;
    }
    for (int64_t r = 0; r < rows; ++r) {
        const double *xr = x + r * cols;
        double *yr = y + r * cols;
        for (int64_t c = 0; c < cols; ++c) {
            yr[c] = z[c] + 0.0 * xr[c];
            z[c] = xr[c] * b1 - yr[c] * a1;
        }
    }
    return 0;
}

/* timing.shifted and then timing.merged in one pass (truckd/ident/timing.py): the
 * sub-intervals of n sample instants t and the m commands issued at t_cmd acting delay s
 * later, in the order a layout keeps (first, stop: the commands acting inside the
 * series; order: the n + stop - first instants sorted; eps: the tie tolerance; lcmd,
 * lse: each of the n + stop - first - 1 sub-intervals' command and sample end), each
 * sub-interval ended by an action instant joined to the next when the commands on both
 * sides have equal inputs a and b.  Writes the joined sub-intervals' durations, commands
 * and sample ends, and returns their count; -1 when the layout's order does not hold
 * under this delay (two instants within eps, or a command crossing the series' ends).
 * The durations are the same differences of the same numbers, a joined one their sum
 * from the left, as numpy computes them. */
int64_t truckd_shift_merge(const double *t, int64_t n, const double *t_cmd, int64_t m,
                           double delay, int64_t first, int64_t stop, const int64_t *order,
                           double eps, const int64_t *lcmd, const int64_t *lse, const double *a,
                           const double *b, double *dt_out, int64_t *cmd_out, int64_t *se_out)
{
    const double t0 = t[0], t1 = t[n - 1];
    const int64_t subs = n + (stop - first) - 1;
    double prev, acc = 0.0;
    int64_t count = 0;
    if (!(t_cmd[first] + delay > t0 && t_cmd[stop - 1] + delay < t1)) {
        return -1;
    }
    if (first > 0 && !(t_cmd[first - 1] + delay <= t0)) {
        return -1;
    }
    if (stop < m && !(t_cmd[stop] + delay >= t1)) {
        return -1;
    }
    prev = order[0] < n ? t[order[0]] : t_cmd[first + order[0] - n] + delay;
    for (int64_t j = 0; j < subs; ++j) {
        const int64_t o = order[j + 1];
        const double next = o < n ? t[o] : t_cmd[first + o - n] + delay;
        const double d = next - prev;
        int join = 0;
        if (!(d > eps)) {
            return -1;
        }
        prev = next;
        acc += d;
        if (j + 1 < subs && lse[j] < 0) {
            const int64_t l = lcmd[j], r = lcmd[j + 1];
            join = l >= 0 && r >= 0 && a[l] == a[r] && b[l] == b[r];
        }
        if (!join) {
            dt_out[count] = acc;
            cmd_out[count] = lcmd[j];
            se_out[count] = lse[j];
            ++count;
            acc = 0.0;
        }
    }
    return count;
}
