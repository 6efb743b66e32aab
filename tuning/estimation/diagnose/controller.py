"""Does the file's controller reproduce its own recorded command? If not, which one ran?

With a recorded command v, the file's PID is run on the recorded position and reference (the
controller saw encoder counts, so this is what it computed, to the clip). A mismatch above 2 %
of the command's range is reported before any plant physics is blamed, and the controller that
ran is inferred: for each derivative form (on error, on measurement) and filter tau on a grid,
a least-squares fit of v = kp e + ki I + kd d over the samples inside the limit; the software
limit is the largest |v| where the command sits at it.

The replay also says whether the controller read the recorded encoder counts (as the hardware's
does) or a finer position (as a simulator that quantizes only what it records): reading the
exact position would have moved its command by about kp q / sqrt(12) RMS, the P term alone.
A replay within a tenth of that says the counts were in the loop, and the diagnosis then
simulates the controller reading them (:func:`reads_counts`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hw.control_law import pid_init, pid_update
from tuning.estimation.engine.noise import encoder_count

TAUS = (0.0, 0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.03, 0.05, 0.1)


def replay(pid, r, y):
    """Commands (after the limit) that ``pid`` computes from recorded r, y."""
    pid = dataclasses.replace(
        pid, **{k: float(getattr(pid, k)) for k in ("kp", "ki", "kd", "tau", "v_limit", "kb")}
    )
    state = pid_init(pid, float(r[0]), float(y[0]))
    out = np.empty(y.size)
    for k in range(y.size):
        u, _, state = pid_update(pid, state, float(r[k]), float(y[k]))
        out[k] = u
    return out


def _regressors(r, y, ts, tau, on):
    e = r - y
    s = e if on == "error" else -y
    integral = np.concatenate([[0.0], np.cumsum(e[:-1]) * ts])
    d = np.zeros_like(e)
    prev, dk = s[0], 0.0
    for k in range(e.size):
        dk = (tau * dk + s[k] - prev) / (tau + ts)
        prev = s[k]
        d[k] = dk
    return np.column_stack([e, integral, d])


def reads_counts(kp: float, mismatch: float, q: float) -> bool:
    """Whether a controller of gain ``kp`` [V/m] whose replay on the recorded counts misses the
    recorded command by ``mismatch`` [V] RMS read those counts (count size ``q`` [m], 0 for
    data that are not counts): the exact position would have changed its P term alone by
    about kp q / sqrt(12) RMS, ten times the tolerance."""
    return q > 0 and mismatch <= 0.1 * abs(kp) * q / math.sqrt(12)


def check(recording):
    """{consistent, mismatch_rms, message, inferred (PID or None), reads_counts} for a closed
    loop with a recorded command; None when there is nothing to check. reads_counts: the
    controller read the recorded encoder counts (:func:`reads_counts`)."""
    pid = recording.controller
    v = recording.command
    if recording.kind != "closed_loop" or v is None or pid is None:
        return None
    r = np.asarray(recording.reference, dtype=float)
    y = np.asarray(recording.position, dtype=float)
    v = np.asarray(v, dtype=float)
    span = max(float(np.ptp(v)), 1e-9)
    mine = replay(pid, r, y)
    mismatch = float(np.sqrt(np.mean((mine - v) ** 2)))
    ok = mismatch <= 0.02 * span + 1e-3
    q = encoder_count(y)
    out = {"consistent": bool(ok), "mismatch_rms": mismatch, "inferred": None}
    name = getattr(recording.path, "name", str(recording.path))
    if ok:
        out["reads_counts"] = reads_counts(float(pid.kp), mismatch, q)
        out["message"] = (
            f"{name}: the file's controller reproduces its recorded command "
            f"(RMS difference {mismatch:.3g} V)" + _counts_note(out["reads_counts"], q)
        )
        return out
    inferred, fit_rms = infer(recording)
    out["inferred"] = inferred
    out["inferred_rms"] = fit_rms
    out["reads_counts"] = reads_counts(inferred.kp, fit_rms, q)
    out["message"] = (
        f"{name}: the file's controller does NOT reproduce its recorded command (RMS "
        f"difference {mismatch:.3g} V of a {span:.3g} V range); inferred from the recorded "
        f"command and error: kp = {inferred.kp:.4g}, ki = {inferred.ki:.4g}, "
        f"kd = {inferred.kd:.4g}, tau = {inferred.tau:.4g} s, derivative on "
        f"{inferred.derivative_on}, v_limit = {inferred.v_limit:.4g} V (replays it to "
        f"{fit_rms:.3g} V); the diagnosis uses the inferred controller"
    ) + _counts_note(out["reads_counts"], q)
    return out


def _counts_note(counts: bool, q: float) -> str:
    if not counts:
        return ""
    return (
        f"; it read the recorded encoder counts ({q * 1e6:.4g} um each), and the simulation "
        "reads them too"
    )


def infer(recording):
    """(PID, RMS of its replay against the recorded command) from recorded v, r, y."""
    pid = recording.controller
    ts = float(recording.sample_time)
    r = np.asarray(recording.reference, dtype=float)
    y = np.asarray(recording.position, dtype=float)
    v = np.asarray(recording.command, dtype=float)
    vmax = float(np.max(np.abs(v)))
    at = np.abs(v) >= vmax * (1 - 1e-6)
    limit = vmax if at.sum() >= 3 else math.inf
    inside = ~at if np.isfinite(limit) else np.ones(v.size, dtype=bool)
    best = None
    for on in ("error", "measurement"):
        for tau in TAUS:
            x = _regressors(r, y, ts, tau, on)[inside]
            coef, *_ = np.linalg.lstsq(x, v[inside], rcond=None)
            res = float(np.sqrt(np.mean((x @ coef - v[inside]) ** 2)))
            if best is None or res < best[0] - 1e-12:
                best = (res, on, tau, coef)
    _, on, tau, (kp, ki, kd) = best
    clean = {
        "kp": float(kp),
        "ki": float(ki) if abs(ki) > 1e-6 * max(abs(kp), 1) else 0.0,
        "kd": float(kd) if abs(kd) > 1e-6 * max(abs(kp), 1) else 0.0,
    }
    new = dataclasses.replace(
        pid, tau=float(tau), derivative_on=on, v_limit=float(limit), anti_windup="none", **clean
    )
    rms = float(np.sqrt(np.mean((replay(new, r, y) - v) ** 2)))
    return new, rms
