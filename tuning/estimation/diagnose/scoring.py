"""How a diagnosis scores a structure: the information criterion on its residuals (each
recording against its own floor, a penalty per value and per part), what a structure must reach
to matter, what repeated runs say the cart repeats, and how much of the located windows' residual
a structure removes."""

from __future__ import annotations

import math

import numpy as np

from tuning.estimation.diagnose.policy import PENALTY_PER_EFFECT, PENALTY_PER_PARAM
from tuning.estimation.engine.noise import repeatability


def rms(parts) -> float:
    r = np.concatenate(parts)
    return float(np.sqrt(np.mean(r * r)))


def score(cand, residuals, noise) -> float:
    """The information criterion of ``cand`` at ``residuals`` [m] (one array per recording;
    in-sample or held out): the recordings' misfit, each against its own floor
    (:meth:`~tuning.estimation.engine.noise.RecordingNoise.misfit`), plus a penalty per free
    value and per part (lower is better)."""
    k = len(cand.free) - 1
    effects = len(cand.parts)
    fit = noise.misfit(residuals)
    return fit + k * PENALTY_PER_PARAM * math.log(noise.total) + effects * PENALTY_PER_EFFECT


def cost_to_reach(cand, reach, noise) -> float:
    """About the largest sum of squared residuals [m^2] at which ``cand`` scores ``reach`` or
    better (0 where its penalties alone score worse): every recording's share of it in
    proportion to its samples and floor (a screen, not a bound)."""
    at_floor = [np.full(int(n), f) for n, f in zip(noise.sizes, noise.floors, strict=True)]
    room = reach - score(cand, at_floor, noise)  # at the floor: the penalties alone
    floor_sse = float(np.sum(noise.sizes * noise.floors**2))
    return floor_sse * math.exp(min(room / noise.total, 700.0)) if room >= 0 else 0.0


def repeat_levels(segments) -> dict:
    """{segment index: what the cart repeats [m]} for runs of one experiment repeated: the
    same kind, sample time, start and controller (every setting), and the same reference or
    input, sample for sample over their common length (a step down is not a repeat of the step
    up: runs that differ would excuse any misfit)."""
    groups: list = []  # (static key, signal) of each experiment seen
    runs = {}
    for i, seg in enumerate(segments):
        exp, c = seg.experiment, seg.controller
        settings = (
            ()
            if c is None
            else tuple(
                (k, v if isinstance(v, str) else float(v)) for k, v in sorted(vars(c).items())
            )
        )
        key = (seg.kind, seg.motor, float(exp.sample_time), round(float(exp.y0), 4), settings)
        signal = np.asarray(exp.signal, dtype=float)
        same = [
            g
            for g, (k, other) in enumerate(groups)
            if k == key
            and np.allclose(other[: signal.size], signal[: other.size], rtol=0, atol=1e-6)
        ]
        if not same:
            groups.append((key, signal))
        runs[i] = (same[0] if same else len(groups) - 1, seg.target)
    return repeatability(runs)


def window_evidence(cands, base, masks) -> None:
    """How much of the located windows' residual energy each candidate removes (0..1)."""
    base_w = sum(float(r[m] @ r[m]) for r, m in zip(base.residuals, masks, strict=True))
    for c in cands:
        cw = sum(float(r[m] @ r[m]) for r, m in zip(c.residuals, masks, strict=True))
        c.window_evidence = 1.0 - cw / base_w if base_w > 0 else 0.0


def window_masks(segments, wins):
    masks = []
    for seg in segments:
        ts = seg.experiment.sample_time
        t = seg.start * ts + np.arange(seg.target.size) * ts
        m = np.zeros(seg.target.size, dtype=bool)
        for w in wins:
            if w["recording"] == seg.name:
                m |= (t >= w["start"] - 1e-9) & (t <= w["end"] + 1e-9)
        masks.append(m)
    return masks


def costs_text(costs) -> str:
    """Mean squared residuals [m^2] as RMS values in mm, for a progress line."""
    return " ".join(f"{math.sqrt(max(c, 0.0)) * 1e3:.3f}" for c in costs) + " mm"
