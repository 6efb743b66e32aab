/* Workload W1 (docs/design.md, "Benchmark workload W1") as a minimal C kernel: the ceiling
 * row of `jaxcart bench`. Exactly the loop of jaxcart.metrics.step_metrics for a linear plant
 * with the exact zero-order-hold step x+ = Ad x + Bd u (Ad[0][0] = 1, Ad[1][0] = 0), the lab's
 * PID (derivative on error, no anti-windup), the software clip at v_limit and an amplifier clip
 * at v_sat, and the streamed step metrics (nothing per sample is stored).
 *
 * Runs are processed LANES at a time, lane loop innermost, so the compiler vectorizes across
 * runs; LANES = 1 is the plain scalar loop. One vector of runs is latency-bound (each sample
 * depends on the last through y -> e -> v -> u -> y): several vectors in flight hide that,
 * 64 float32 / 16 float64 lanes measured fastest on AVX-512 (of 16-128 / 8-32).
 * Both precisions are built: w1_f32_*, w1_f64_*. Units: SI (m, s, V).
 *
 * Outputs per run (arrays of n_runs): rise, settling, overshoot [%], sse [m], peak_v [V],
 * sat_time [s], diverged (0/1). trace (record runs x n samples) receives y_k of the first
 * `record` runs, for the check against the float64 reference.
 */
#include <math.h>
#include <stdint.h>

#define W1_KERNEL(REAL, NAME, LANES)                                                           \
void NAME(int64_t n_runs, const REAL *gains, int64_t n, const REAL *r, const REAL *coef,       \
          REAL *rise, REAL *settling, REAL *overshoot, REAL *sse, REAL *peak_v,               \
          REAL *sat_time, uint8_t *diverged, int64_t record, REAL *trace)                      \
{                                                                                              \
    /* coef: ts, tau, gain = 1/(tau+ts), v_lim, v_sat, limit, a01, a11, b0,   \
       b1, y0, yd0, inv_amplitude, band, diverged position */                                  \
    const REAL ts = coef[0], tau = coef[1], gain = coef[2], v_lim = coef[3], v_sat = coef[4]; \
    const REAL limit = coef[5], a01 = coef[6], a11 = coef[7], b0 = coef[8], b1 = coef[9];      \
    const REAL y0 = coef[10], yd0 = coef[11], inv_amp = coef[12], band = coef[13];            \
    const REAL big = coef[14], r_final = r[n - 1];                                             \
    const REAL inf = (REAL)INFINITY;                                                           \
    for (int64_t start = 0; start < n_runs; start += LANES) {                                  \
        REAL kp[LANES], kd[LANES], ki[LANES], y[LANES], yd[LANES], integ[LANES];               \
        REAL deriv[LANES], prev[LANES], peak[LANES], pv[LANES], ylast[LANES];                 \
        int32_t k10[LANES], k90[LANES], last_out[LANES], n_sat[LANES], bad[LANES];             \
        for (int j = 0; j < LANES; j++) {                                                      \
            /* Lanes past the end repeat the last run (computed, never written). */           \
            int64_t i = start + j < n_runs ? start + j : n_runs - 1;                           \
            kp[j] = gains[3 * i]; kd[j] = gains[3 * i + 1]; ki[j] = gains[3 * i + 2];          \
            y[j] = y0; yd[j] = yd0; integ[j] = 0; deriv[j] = 0; prev[j] = r[0] - y0;           \
            peak[j] = -inf; pv[j] = 0;                                                         \
            k10[j] = -1; k90[j] = -1; last_out[j] = -1; n_sat[j] = 0; bad[j] = 0;              \
        }                                                                                      \
        for (int64_t k = 0; k < n; k++) {                                                      \
            const REAL rk = r[k];                                                              \
            const int32_t kk = (int32_t)k;                                                     \
            if (start < record)  /* outside the lane loop, which stays branch-free */         \
                for (int j = 0; j < LANES && start + j < record; j++)                          \
                    trace[(start + j) * n + k] = y[j];                                         \
            for (int j = 0; j < LANES; j++) {                                                  \
                REAL e = rk - y[j];                                                            \
                ylast[j] = y[j];                                                               \
                REAL d = (tau * deriv[j] + e - prev[j]) * gain;                               \
                REAL v = kp[j] * e + ki[j] * integ[j] + kd[j] * d;                             \
                REAL u = v > v_lim ? v_lim : (v < -v_lim ? -v_lim : v);                        \
                u = u > v_sat ? v_sat : (u < -v_sat ? -v_sat : u);                             \
                integ[j] += ts * e; deriv[j] = d; prev[j] = e;                                 \
                /* Streamed metrics of y_k (the definitions of step_metrics). */              \
                REAL z = (y[j] - y0) * inv_amp;                                                \
                k10[j] = ((k10[j] < 0) & (z >= (REAL)0.1)) ? kk : k10[j];                      \
                k90[j] = ((k90[j] < 0) & (z >= (REAL)0.9)) ? kk : k90[j];                      \
                REAL dist = y[j] - r_final;                                                    \
                last_out[j] = ((dist > band) | (dist < -band)) ? kk : last_out[j];             \
                peak[j] = z > peak[j] ? z : peak[j];                                           \
                n_sat[j] += (v > limit) | (v < -limit);                                        \
                REAL au = u < 0 ? -u : u;                                                      \
                pv[j] = au > pv[j] ? au : pv[j];                                               \
                bad[j] |= !((y[j] <= big) & (y[j] >= -big));                                   \
                /* Exact ZOH step of the plant over one sample. */                            \
                y[j] += a01 * yd[j] + b0 * u;                                                  \
                yd[j] = a11 * yd[j] + b1 * u;                                                  \
            }                                                                                  \
        }                                                                                      \
        for (int j = 0; j < LANES && start + j < n_runs; j++) {                                \
            int64_t i = start + j;                                                             \
            int b = bad[j];                                                                    \
            REAL t10 = k10[j] < 0 ? inf : (REAL)k10[j] * ts;                                   \
            REAL t90 = k90[j] < 0 ? inf : (REAL)k90[j] * ts;                                   \
            REAL st = last_out[j] < 0 ? 0 : (last_out[j] + 1 >= n ? inf                        \
                                              : (REAL)(last_out[j] + 1) * ts);                 \
            rise[i] = (b || k90[j] < 0) ? inf : t90 - t10;                                     \
            settling[i] = b ? inf : st;                                                        \
            REAL os = (peak[j] - 1) * 100;                                                     \
            overshoot[i] = b ? inf : (os > 0 ? os : 0);                                        \
            peak_v[i] = pv[j];                                                                 \
            sat_time[i] = (REAL)n_sat[j] * ts;                                                 \
            diverged[i] = (uint8_t)b;                                                          \
            REAL err = r_final - ylast[j];                                                     \
            sse[i] = b ? inf : (err < 0 ? -err : err);                                         \
        }                                                                                      \
    }                                                                                          \
}

W1_KERNEL(float, w1_f32_lanes, 64)
W1_KERNEL(double, w1_f64_lanes, 16)
W1_KERNEL(float, w1_f32_scalar, 1)
W1_KERNEL(double, w1_f64_scalar, 1)
