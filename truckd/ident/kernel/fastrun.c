/* The free-run loop of truckd/ident/freerun.py (function run) in C, for the fitting loop.
 *
 * Same arithmetic, same order, as the Python reference: a first-order drivetrain with
 * Coulomb friction and stiction, each sub-interval solved exactly (truckd/ident/freerun.py
 * explains the model).  The Python loop stays the reference and the fallback; tests
 * check both give the same speeds (tests/test_ident_kernel.py).  Pure computation.
 */
#include <math.h>
#include <stdint.h>

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

/* One segment of length h: end speed, *dist = integral of speed. */
static double segment(double w, double a, double b, double c, double sigma, double d, double h,
                      double lag, double *dist)
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
            extra = 0.0;
            if (fabs(net) <= sigma) {
                return 0.0;
            }
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

/* See freerun.run.  scale may be NULL (1 everywhere), ter NULL (no terrain).  Returns 0. */
int truckd_fastrun(const double *a, const double *b, double a_idle, double b_idle, double kc,
                   double ksigma, double kd, double kdrag, const double *scale, double lag,
                   const double *dt, const int64_t *cmd, const int64_t *sample_end, int64_t m,
                   int64_t n, double w0, double sensor_lag, double *out, double *raw, double *pos,
                   const double *ter)
{
    double w = w0, v_lag = w0, x = 0.0, x_step0 = 0.0, h_step = 0.0;
    double c = kc, sigma = ksigma, d = kd, drag = kdrag;
    double last_h = -1.0, last_alpha = 0.0;
    if (n < 1) {
        return 0;
    }
    out[0] = raw[0] = w0;
    pos[0] = 0.0;
    for (int64_t j = 0; j < m; ++j) {
        double h = dt[j], aa, bb, b_eff, d_eff, bh;
        int64_t k = cmd[j], se = sample_end[j];
        double f = 1.0;
        if (k >= 0) {
            aa = a[k];
            bb = b[k];
            if (scale != 0) {
                f = scale[k];
                c = kc * f;
                sigma = ksigma * f;
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
        if (drag != 0.0) {
            double aw = fabs(w);
            b_eff = bb + 2.0 * drag * aw;
            d_eff = d - drag * w * aw;
        } else {
            b_eff = bb;
            d_eff = d;
        }
        bh = b_eff * h;
        if (w != 0.0 && bh >= 1e-5) {
            double s = w > 0.0 ? 1.0 : -1.0;
            double g = aa - s * c - d_eff;
            double em1 = -expm1(-bh);
            double p1 = em1 / b_eff;
            double w1 = w * (1.0 - em1) + g * p1;
            if (w1 * s > 0.0) {
                x += w * p1 + g * (h - p1) / b_eff;
                w = w1;
            } else {
                double dx;
                w = segment(w, aa, b_eff, c, sigma, d_eff, h, lag, &dx);
                x += dx;
            }
        } else {
            double dx;
            w = segment(w, aa, b_eff, c, sigma, d_eff, h, lag, &dx);
            x += dx;
        }
        h_step += h;
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
    return 0;
}
