"""Where a fit starts: values read off the recordings, so that the fits begin in the basin of
the data rather than at the handout's numbers.

A closed loop with stick-slip is many-basined: on a PI loop hunting by stiction (f_c 1.0 N,
f_s 2.2 N, B_eq 4.6 kg/s), the exact fit from the true friction levels and the handout's B_eq
5.4 kg/s ends at B_eq 15.6 kg/s and 0.56 mm, from B_eq 4.6 kg/s at the encoder floor. The
recordings say where to start:

- :func:`motion_regression`: the cart's own equation, m y'' + (B_eq + B_emf) y' + f_c sign(y')
  = gamma u, solved by least squares for B_eq and f_c over the samples where the cart moves
  and the drive is below its largest command (a limit's corner biases what is above);
- :func:`held_force`: the largest drive force a recorded command held the cart at rest with,
  where a breakaway (static) level starts (``Param.starts_at = "held"``);
- a limit below the largest command (:func:`~tuning.estimation.engine.parameters.start_for`).
"""

from __future__ import annotations

import numpy as np

from jaxcart.exact import simulate_exact
from tuning.estimation.engine import parameters

#: A cart is at rest where its recorded position stays put this long [s].
AT_REST = 0.02
#: The regression's velocity and acceleration are central differences over this span [s]
#: (encoder counts of 23 um at 1 kHz: over 10 ms a velocity of 0.02 m/s spans 9 counts).
SPAN = 0.01
#: Samples where the cart moves faster than this [m/s] enter the regression.
MOVING = 0.01
#: ... and where the command is below this share of the recording's largest (a drive limit
#: clips what is above it, which the regression does not model).
BELOW_PEAK = 0.7


def start_values(segments, recs, base_plants, free) -> dict:
    """Start values [SI] of the parameters ``free`` of a diagnosis of ``segments`` (prepared
    from ``recs``, on ``base_plants``): B_eq and f_c from :func:`motion_regression` where it
    is determined and plausible, else the handout's B_eq and f_c's declared start; limits and
    breakaway levels from the data (:func:`~.parameters.start_for`); else declared."""
    u_max = 0.0
    for rec, seg in zip(recs, segments, strict=True):
        if rec.command is not None:
            u_max = max(u_max, float(np.max(np.abs(rec.command))))
        elif seg.motor:
            res = simulate_exact(base_plants[0], seg.controller, seg.experiment)
            u_max = max(u_max, float(np.nanmax(np.abs(res.command))))
    u_max = max(u_max, 0.5)
    ymean = float(np.mean(np.concatenate([s.target for s in segments])))
    motor = any(s.motor for s in segments)
    peaks = {
        "command": u_max,
        "current": u_max / float(base_plants[0].Rm),
        "held": held_force(segments, recs, base_plants),
    }
    start = {"B_eq": 5.4 if motor else 2.0, "M": 0.94, "gamma_scale": 1.0}
    start.update(read_off(segments, recs, base_plants))
    for n in free:
        if n not in start:
            start[n] = parameters.start_for(n, peaks, ymean)
    return {k: start[k] for k in free}


def read_off(segments, recs, base_plants) -> dict:
    """{"B_eq", "f_c"} [SI] of :func:`motion_regression` that are positive and plausible for a
    cart of this lab (each left out where it is not): where every fit of the engine starts
    them unless it is given them."""
    found = motion_regression(segments, recs, base_plants)
    return {n: v for n, v in found.items() if parameters.plausible(n, v) and v > 0}


def read_off_each(segments, recs, base_plants, names) -> list:
    """The values of ``names`` (of B_eq, f_c) :func:`read_off` every recording together, then
    off each one alone where they differ: [{name: value}, ...] ([] where none is read), the
    starts a fit chooses among by its objective (together, a long run the model cannot follow
    outvotes a tap as a sum of squares does)."""
    groups = [(segments, recs, base_plants)]
    if len(segments) > 1:
        groups += [([s], [r], [p]) for s, r, p in zip(segments, recs, base_plants, strict=True)]
    out = []
    for group in groups:
        found = {n: v for n, v in read_off(*group).items() if n in names}
        if found and found not in out:
            out.append(found)
    return out


def motion_regression(segments, recs, base_plants) -> dict:
    """{"B_eq" [kg/s], "f_c" [N]} from m y'' + (B_eq + B_emf) y' + f_c sign(y') = gamma u
    (u = 0 on a tap) over every recording's moving samples (faster than MOVING, the command
    below BELOW_PEAK of its largest), velocity and acceleration central differences over SPAN;
    {} with fewer than 50 such samples."""
    rows, rhs = [], []
    for rec, seg, plant in zip(recs, segments, base_plants, strict=True):
        if seg.motor and rec.command is None:
            continue
        ts = float(seg.experiment.sample_time)
        k = max(int(round(SPAN / ts)), 1)
        y = np.asarray(seg.target, dtype=float)
        if y.size <= 2 * k:
            continue
        v = (y[2 * k :] - y[: -2 * k]) / (2 * k * ts)
        a = (y[2 * k :] - 2 * y[k:-k] + y[: -2 * k]) / (k * ts) ** 2
        u = np.zeros_like(v)
        if seg.motor:
            cmd = np.asarray(rec.command, dtype=float)[seg.start :][: y.size]
            if cmd.size < y.size:
                continue
            u = cmd[k:-k]
        keep = (np.abs(v) > MOVING) & (np.abs(u) <= BELOW_PEAK * max(np.max(np.abs(u)), 1e-9))
        b_emf = float(plant.B_emf) if seg.motor else 0.0
        rows.append(np.column_stack([v[keep], np.sign(v[keep])]))
        rhs.append(float(plant.gamma) * u[keep] - float(plant.m) * a[keep] - b_emf * v[keep])
    if not rows or sum(r.shape[0] for r in rows) < 50:
        return {}
    (b_eq, f_c), *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
    return {"B_eq": float(b_eq), "f_c": float(f_c)}


def held_force(segments, recs, base_plants) -> float:
    """The largest drive force [N], gamma |u|, that a recorded command held the cart at rest
    with (its position unchanged over AT_REST), over the driven recordings; 0 without one."""
    held = 0.0
    for rec, seg, plant in zip(recs, segments, base_plants, strict=True):
        if rec.command is None or not seg.motor:
            continue
        u = np.abs(np.asarray(rec.command, dtype=float)[seg.start :][: seg.target.size])
        y = seg.target[: u.size]
        w = max(int(AT_REST / float(seg.experiment.sample_time)), 1)
        if y.size <= w:
            continue
        still = np.ptp(np.lib.stride_tricks.sliding_window_view(y, w + 1), axis=1) == 0
        if np.any(still):
            held = max(held, float(plant.gamma) * float(np.max(u[: still.size][still])))
    return held
