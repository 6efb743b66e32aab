"""A candidate structure's runs on the exact simulator: each recording's plant at its values, the
runs (made several at a time and kept in a memo), their residuals, and the exact polish of the
values with its forward-difference Jacobian."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from jaxcart.exact import simulate_exact
from jaxcart.plantspec import build_plant
from tuning.estimation.diagnose.structures import PER_RUN, Candidate, params_of, per_run_params
from tuning.estimation.engine import exact_polish, parameters
from tuning.estimation.engine.exact_runs import (
    ExactJob,
    ExactMemo,
    exact_run,
    read_only,
)


def exact_plants(cand: Candidate, base_plants, values):
    """Each recording's plant at ``values``: the shared values, and a run's own copy of a
    parameter free per run (``v_sat@2``) where it has one."""
    named = {n: values[n] for n in cand.free if "@" not in n}
    named["B_eq"] = values["B_eq"]
    plants = []
    for i, p in enumerate(base_plants):
        own = {parameters.base_name(k): v for k, v in values.items() if k.endswith(f"@{i}")}
        own = {k: v for k, v in own.items() if k in per_run_params()}
        if PER_RUN in cand.parts and not own:
            # A run without its own copy (a tap): the drive limits do not act there.
            own = {n: parameters.stand_in(n) for n in per_run_params() if n in params_of(cand)}
        plants.append(build_plant(parameters.consistent({**named, **own}), base=p, check=False))
    return plants


def started(experiment, starts, values: dict, i: int):
    """``experiment`` from recording ``i``'s start values in ``values`` (``y0@0``), for each
    fitted start of ``starts`` (a :class:`~tuning.estimation.engine.layout.Layout`'s)."""
    given = {v: values[f"{v}@{i}"] for v, _ in starts if f"{v}@{i}" in values}
    return dataclasses.replace(experiment, **given) if given else experiment


def exact_jobs(cand, segments, base_plants, values, layout) -> list:
    """(memo key, :class:`ExactJob`) of each recording of ``cand`` at ``values``."""
    plants = exact_plants(cand, base_plants, values)
    out = []
    for i, (seg, plant) in enumerate(zip(segments, plants, strict=True)):
        exp = started(seg.experiment, layout.starts[i], values, i)
        job = ExactJob(seg.controller, plant, exp, seg.target, seg.counts_in_loop, seg.motor)
        out.append(((i, plant, exp.y0, exp.yd0), job))
    return out


def exact_residuals(cand, segments, base_plants, values, layout, memo: ExactMemo | None = None):
    """Exact-simulator residuals [m] (and commands [V] of motor segments) of ``cand`` at
    ``values``, one array per segment; ``memo`` reuses a run made before (of all recordings,
    or of one recording whose plant and start are unchanged). The recordings' runs are made
    several at a time (the memo's executor)."""
    jobs = exact_jobs(cand, segments, base_plants, values, layout)
    if memo is None:
        runs = [read_only(exact_run(j)) for _, j in jobs]
        return [r for r, _ in runs], [u for _, u in runs]

    def compute():
        memo.fill(jobs)
        runs = [memo.segment(key, lambda job=job: exact_run(job)) for key, job in jobs]
        return [r for r, _ in runs], [u for _, u in runs]

    return memo.get(cand, values, compute)


def exact_prefetch(cand, segments, base_plants, many, layout, memo: ExactMemo) -> None:
    """Make the runs of ``cand`` at each of ``many`` (a list of values) at once, into ``memo``
    (a forward-difference Jacobian's columns: several run at a time)."""
    memo.fill([j for v in many for j in exact_jobs(cand, segments, base_plants, v, layout)])


def plant_of(cand, base_plants, segments):
    """The plant of ``cand`` at its values (the first motor segment's)."""
    plants = exact_plants(cand, base_plants, cand.values)
    motor = [p for p, s in zip(plants, segments, strict=True) if s.motor]
    return motor[0] if motor else plants[0]


def current_peaks(cand, segments, base_plants, values, layout) -> dict:
    """Largest |armature current| [A] of each motor segment's exact run under ``cand``,
    i = (v - (B_emf/gamma) y')/Rm at the samples: {segment index: peak}."""

    peaks = {}
    plants = exact_plants(cand, base_plants, values)
    for i, (seg, plant) in enumerate(zip(segments, plants, strict=True)):
        if not seg.motor:
            continue
        exp = started(seg.experiment, layout.starts[i], values, i)
        res = simulate_exact(plant, seg.controller, exp)
        k_b = float(plant.B_emf) / float(plant.gamma)
        i_arm = (np.asarray(res.voltage) - k_b * np.asarray(res.velocity)) / float(plant.Rm)
        peaks[i] = float(np.nanmax(np.abs(i_arm))) if np.any(np.isfinite(i_arm)) else 0.0
    return peaks


def polish(
    cand, segments, base_plants, values, layout, iterations=3, memo=None, target=None, weights=None
):
    """The engine's exact polish (:func:`~tuning.estimation.engine.exact_polish.polish`:
    Gauss-Newton on the exact simulator, forward differences, within the bounds) in the values
    themselves, a few parameters; ``weights``: each recording's weight in the joint least
    squares (:meth:`~tuning.estimation.engine.noise.RecordingNoise.weights`; equal when None).
    Returns (values, the forward-difference Jacobian of the exact residual [m per unit of each
    value] at them or None, the values' names in its column order, whether it converged);
    ``target``: the (weighted) cost worth fitting for (see there)."""
    names = list(values)
    roots = np.sqrt(np.ones(len(segments)) if weights is None else np.asarray(weights))
    rows = np.concatenate([np.full(s.target.size, w) for s, w in zip(segments, roots, strict=True)])

    def at(x):
        return dict(zip(names, (float(v) for v in x), strict=True))

    def residuals(xs):
        if memo is not None and len(xs) > 1:  # the runs of every point made at once
            exact_prefetch(cand, segments, base_plants, [at(x) for x in xs], layout, memo)
        # Through the memo: a difference in a per-run value re-simulates its own run alone.
        parts = [exact_residuals(cand, segments, base_plants, at(x), layout, memo)[0] for x in xs]
        return [np.concatenate(p) for p in parts]

    done = exact_polish.polish(
        residuals, names, [values[n] for n in names], iterations,
        reference=smooth_reference(cand, names, values, segments), target=target, rows=rows,
    )  # fmt: skip
    out = at(done.x) if done.improved else values
    return out, done.jac, names, done.converged


def smooth_reference(cand, names, values, segments):
    """Column norms of ``cand``'s batch-fit Jacobian (its free slots, then the nuisances) per
    unit of each value of ``names`` (0 where it has none): where the smooth model sees a value
    act, a flat exact difference quotient is the staircase (the exact polish's ``reference``,
    :func:`~tuning.estimation.engine.exact_polish.polish`)."""
    slopes = np.array([parameters.value_slope(n, values[n]) for n in names])
    jac = getattr(cand, "jac", None)
    order = list(cand.free) + [n for n in names if n not in cand.free]
    if jac is None or jac.ndim != 2 or jac.shape[1] < len(order):
        return np.zeros(len(names))
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.linalg.norm(jac, axis=0) / fitter_scale(segments)
    norms = np.where(np.isfinite(norms), norms, 0.0)  # a smooth fit that ran away says nothing
    return np.array(
        [
            norms[order.index(n)] / abs(slope) if slope else 0.0
            for n, slope in zip(names, slopes, strict=True)
        ]
    )


def theta_jacobian(cand, jac, order, values, nuis, segments) -> np.ndarray:
    """The exact re-fit's forward-difference Jacobian (columns in ``order``, per unit of each
    value) in the form of the batch fit's: columns the candidate's free slots and the
    nuisances, per unit of the fitted parameter (its logarithm for a log-fitted one), times
    :func:`fitter_scale`. An empty array where the re-fit made none or lacks a column."""
    names = list(cand.free) + list(nuis)
    if jac is None or any(n not in order for n in names):
        return np.zeros((0, 0))
    cols = [jac[:, order.index(n)] * parameters.value_slope(n, values[n]) for n in names]
    return fitter_scale(segments) * np.column_stack(cols)


def fitter_scale(segments) -> float:
    return 1.0 / math.sqrt(sum(s.target.size for s in segments))
