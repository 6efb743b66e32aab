"""The gradient tuner raced against gradient-free baselines on the same problem, in one run
(``jaxcart tune --compare``): scipy's Nelder-Mead on the exact simulator, and for the lab's
problem the best point of a quasi-random (Sobol) grid on the batched hard-clip simulator given
the tuner's wall time. Wall times include compilation.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy.optimize import minimize
from scipy.stats import qmc

from hw.control_law import PID, float_pid
from jaxcart.batch_metrics import step_metrics_batch
from jaxcart.errors import UserError
from jaxcart.experiments import step
from jaxcart.params import Plant
from jaxcart.plantspec import build_plant, handout_plant
from jaxcart.smooth_sim import EXACT_FORMS
from tuning.design.candidates import exact_info, failing_constraints, violation, worst
from tuning.design.for_cart import training_carts
from tuning.design.iteration import SCALES
from tuning.design.losses import (
    GAIN_NAMES,
    PARAM_NAMES,
    LossSettings,
    Spec,
    controller_with,
    params_of,
)
from tuning.design.problem import (
    DEFAULT_ROBUST,
    base_start,
    free_mask,
    has_force_effects,
    robust_plants,
    search_box,
    start_and_template,
)
from tuning.design.result import json_number
from tuning.design.tune import tune
from tuning.design.uncertainty import from_fit_table

#: Box of the grid baseline, sampled log-uniformly: kp [V/m], kd [V s/m], ki [V/(m s)] generous
#: around the handout's gains, without the useless corners of DEFAULT_BOUNDS; and where they
#: are tuned too, tau [s], kb [1/s] and v_limit [V] (the tuner's box, within reason).
GRID_BOX = {
    "kp": (10.0, 1000.0),
    "kd": (0.5, 50.0),
    "ki": (0.01, 50.0),
    "tau": (1e-3, 0.05),
    "kb": (0.1, 100.0),
    "v_limit": (3.0, 6.0),
}


def penalty_objective(
    settling, overshoot, steady_state_error, spec: Spec, settings: LossSettings | None = None
) -> float:
    """The tuning loss on exact metrics (for gradient-free baselines): settling / T_max plus
    the same hinge penalties; a run that never settles counts as horizon x (1 + final error in
    band widths), so the objective still slopes where the settling time is inf."""
    settings = settings or LossSettings()
    settling = float(settling)
    if not math.isfinite(settling):
        error = min(float(steady_state_error), 1e3) / (spec.band * abs(spec.step))
        settling = spec.horizon * (1.0 + error)
    ts = settling / spec.settling_time
    os = min(float(overshoot), 1e4) / spec.overshoot
    return ts + settings.weight * (max(os - settings.target, 0.0) + max(ts - settings.target, 0.0))


#: The benchmark problems of :func:`compare_tuners`: the lab's (kp, kd, ki on the nominal
#: plant); robust over 25 plants (the default box's centre and 8 corners, plus 16 random
#: plants of it); wide: all six numbers of the PID (kp, kd, ki, tau, kb with back-calculation
#: anti-windup, v_limit) robust over the box's centre and corners (9 plants); cart: the six
#: numbers robust over :data:`CART_CARTS` carts drawn from a fitted cart's uncertainty (the
#: design for the cart as measured, :mod:`tuning.design.for_cart`: a plant file's, or the real
#: recordings' cart, :func:`real_cart`).
PROBLEMS = ("lab", "robust", "wide", "cart")
#: Most Nelder-Mead evaluations per problem (each one is a run per plant on the exact
#: simulator), and the most seconds it may take.
NM_EVALUATIONS = {"lab": 600, "robust": 400, "wide": 600, "cart": 600}
NM_SECONDS = 600.0
#: The methods of a comparison, and how a table names them.
METHODS = {
    "gradient": "gradient (this tuner, exact check)",
    "nelder_mead": "scipy Nelder-Mead, exact simulator",
    "grid": "Sobol grid, equal wall time",
}
#: Carts of the cart problem: the fitted one and those drawn from its uncertainty.
CART_CARTS = 24
#: The cart of the lab's real recordings (a tap, a P 50 step and its repeat; docs/diagnose.md),
#: as ``jaxcart lab`` fitted it at 491d7e4: B_eq [kg/s], f_c [N], delay [s] with their
#: standard errors, and the amplifier's limit [V] of each driven run (the plant file's [fit]
#: table, cart_plant.toml).
REAL_CART = {
    "values": dict(B_eq=1.5165, f_c=0.43274, delay=0.011877, v_sat=5.0884),
    "fit": {
        "stderr": dict(B_eq=0.023834, f_c=0.0082284, delay=0.00062231),
        "runs": dict(v_sat=[5.0884, 5.8964]),
        "runs_stderr": dict(v_sat=[0.033325, 0.016767]),
    },
}


def real_cart():
    """The real recordings' cart with its uncertainty (:data:`REAL_CART`)."""
    plant = build_plant(REAL_CART["values"], where="the real recordings' cart")
    return from_fit_table(plant, REAL_CART["fit"], source="the real recordings (REAL_CART)")


def compare_problem(problem: str, plant: Plant | None = None, *, seed: int = 0, uncertainty=None):
    """(free, controller, robust, n_check, plants, starts) of a benchmark problem of
    :data:`PROBLEMS` on ``plant`` (default the handout's): ``robust`` and ``n_check`` as
    :func:`tune` takes them (False for the lab problem), ``plants`` the set every result is
    judged on (None: the plant alone), the same set tune checks on. The cart problem draws its
    carts from ``uncertainty`` (a :class:`tuning.design.uncertainty.CartUncertainty`; default
    :func:`real_cart`), the first of them the fitted cart."""
    plant = handout_plant() if plant is None else plant
    if problem == "cart":
        u = uncertainty if uncertainty is not None else real_cart()
        plants = training_carts(u, CART_CARTS - 1, seed=seed)
        pid = PID(tau=0.01, v_limit=6.0, kb=1.0, anti_windup="back_calculation")
        return PARAM_NAMES, pid, plants, 0, plants, 4
    if problem == "lab":
        return GAIN_NAMES, None, False, 0, None, 8
    if problem == "robust":
        # The gradient tuner trains on the box's centre and corners and is judged, like
        # Nelder-Mead, on those and 16 random plants: 25.
        plants, _ = robust_plants(plant, DEFAULT_ROBUST, n_random=16, seed=seed + 1)
        return GAIN_NAMES, None, DEFAULT_ROBUST, 16, plants, 2
    if problem == "wide":
        plants, _ = robust_plants(plant, DEFAULT_ROBUST)
        pid = PID(tau=0.01, v_limit=6.0, kb=1.0, anti_windup="back_calculation")
        return PARAM_NAMES, pid, DEFAULT_ROBUST, 0, plants, 4
    raise UserError(f"--problem {problem}: use one of {', '.join(PROBLEMS)}")


def compare_tuners(
    plant: Plant | None = None,
    *,
    problem: str = "lab",
    spec: Spec | None = None,
    start=None,
    free: Sequence[str] | None = None,
    controller: PID | None = None,
    seed: int = 0,
    bounds: Mapping | None = None,
    nm_max_evaluations: int | None = None,
    nm_max_seconds: float = NM_SECONDS,
    grid: bool | None = None,
    progress: bool = False,
    uncertainty=None,
) -> dict:
    """Benchmark :func:`tune` against scipy's Nelder-Mead on the exact simulator, in one run.

    problem: one of :data:`PROBLEMS` (its free parameters, controller and plant set, unless
    ``free`` / ``controller`` are given). Nelder-Mead minimizes the same penalty objective
    (:func:`penalty_objective`, of the worst case over the plant set) on the exact simulator,
    from the same start, in log parameters projected into the same box (``bounds``, default
    :data:`DEFAULT_BOUNDS`). For the lab problem (and ``grid=True``) a third row is the best
    point of a quasi-random (Sobol) grid over :data:`GRID_BOX` on the batched hard-clip
    simulator for the same wall time as :func:`tune` took. Wall times include compilation.

    Returns a dict: one entry per method (settling_time [s], overshoot [%]: exact, worst over
    the set; seconds, seconds_to_spec, evaluations, gains, and for Nelder-Mead
    seconds_to_gradient: when its best point first matched the gradient result's worst-case
    settling time, to 0.5 ms, or None), "ratios" and a printable "table".
    """
    spec = spec or Spec()
    plant = handout_plant() if plant is None else plant
    p_free, p_controller, robust, n_check, plants, n_starts = compare_problem(
        problem, plant, seed=seed, uncertainty=uncertainty
    )
    if problem == "cart":
        plant = plants[0]  # the fitted cart
    free = tuple(free or p_free)
    mask = free_mask(free)
    start_params, template = start_and_template(start, controller or p_controller, free)
    template = float_pid(template)
    experiment = step(spec.step, horizon=spec.horizon, sample_time=template.sample_time)
    check = plants if plants is not None else [plant]
    say = (
        (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)
    )

    # 1. Gradient tuning (this module).
    say(f"compare ({problem}): gradient tuner ...")
    ours = tune(
        plant,
        spec=spec,
        start=start,
        free=free,
        controller=template,
        robust=robust,
        n_check=n_check,
        n_starts=n_starts,
        seed=seed,
        bounds=bounds,
        progress=progress,
    )
    ours_info = ours.worst if ours.worst is not None else ours.exact
    log_lo, log_hi, _, _ = search_box(plant, template, spec, free, bounds)

    # 2. Nelder-Mead on the exact simulator, penalty objective, same start.
    say(f"compare ({problem}): Nelder-Mead on the exact simulator, {len(check)} plant(s) ...")
    nm = _nelder_mead(
        _NelderMeadProblem(template, experiment, spec, check, mask, start_params),
        (log_lo, log_hi),
        # The gradient result's worst-case settling time, to half a sample, where it meets
        # the specification: the point Nelder-Mead's time to it is measured at.
        target=(
            None
            if failing_constraints(ours_info, spec)
            else float(ours_info.settling_time) + 0.5 * template.sample_time
        ),
        max_evaluations=nm_max_evaluations or NM_EVALUATIONS[problem],
        max_seconds=nm_max_seconds,
    )

    # 3. Quasi-random grid on the batched simulator for the same wall time (lab problem).
    grid_entry = None
    if (problem in ("lab", "cart")) if grid is None else grid:
        say(f"compare ({problem}): grid of equal wall time ({ours.seconds:.1f} s) ...")
        grid_entry = _grid_baseline(
            check if plants is not None else plant,
            template,
            experiment,
            spec,
            mask,
            start_params,
            log_lo,
            log_hi,
            ours.seconds,
            seed,
        )
    return _comparison(problem, free, len(check), spec, ours, ours_info, nm, grid_entry)


class _NelderMeadProblem(NamedTuple):
    """What Nelder-Mead tunes: the controller template, the experiment, the specification,
    the plants judged (worst case), which parameters are free and where they start."""

    template: PID
    experiment: object
    spec: Spec
    plants: list
    free_mask: np.ndarray
    start_params: np.ndarray


class _Done(Exception):
    """Nelder-Mead's time cap was reached."""


def _nelder_mead(
    nmp: _NelderMeadProblem, log_box, *, target, max_evaluations: int, max_seconds: float
) -> dict:
    """scipy's Nelder-Mead on the exact simulator: the penalty objective of the worst case
    over the plants, in the logs of the free parameters projected into ``log_box``. Returns
    {params, info (exact StepInfo of the best point), seconds, first_feasible [s],
    evaluations, to_gradient: when the best point first reached ``target`` settling time [s]
    (None: never, or no target), stopped: why it stopped}."""
    spec, mask = nmp.spec, nmp.free_mask
    log_lo, log_hi = log_box
    base = base_start(mask, nmp.start_params)
    nm = {"evaluations": 0, "best": None, "first_feasible": None, "to_gradient": None}
    t0 = time.perf_counter()

    def objective(x):
        if time.perf_counter() - t0 > max_seconds:
            raise _Done
        g = base.copy()
        # Projected into the tuner's box, so both search the same parameters.
        g[mask] = np.exp(np.clip(x, log_lo[mask], log_hi[mask]))
        pid = controller_with(nmp.template, list(g))
        info = worst([exact_info(p, pid, nmp.experiment) for p in nmp.plants])
        nm["evaluations"] += 1
        feasible = not failing_constraints(info, spec)
        now = time.perf_counter() - t0
        if feasible and nm["first_feasible"] is None:
            nm["first_feasible"] = now
        reached = target is not None and info.settling_time <= target
        if feasible and reached and nm["to_gradient"] is None:
            nm["to_gradient"] = now
        key = (
            0 if feasible else 1,
            float(info.settling_time)
            if feasible
            else violation(info.settling_time, info.overshoot, spec),
        )
        if nm["best"] is None or key < nm["best"][0]:
            nm["best"] = (key, g.copy(), info)
        return penalty_objective(info.settling_time, info.overshoot, info.steady_state_error, spec)

    x0 = np.log(base[mask])
    # Initial simplex: +/- 30 % steps in each log parameter (scipy's 5 % is too timid here).
    simplex = np.vstack([x0] + [x0 + 0.3 * np.eye(x0.size)[i] for i in range(x0.size)])
    options = {"maxfev": max_evaluations, "xatol": 1e-3, "fatol": 1e-4, "initial_simplex": simplex}
    try:
        minimize(objective, x0, method="Nelder-Mead", options=options)
        stopped = "converged or evaluation cap"
    except _Done:
        stopped = f"time cap {max_seconds:g} s"
    _, params, info = nm.pop("best")
    return {
        **nm,
        "params": params,
        "info": info,
        "seconds": time.perf_counter() - t0,
        "stopped": stopped,
    }


def _entry(params, info, seconds, to_spec, evaluations, spec: Spec) -> dict:
    """One method's row of :func:`compare_tuners`."""
    return {
        "gains": None
        if params is None
        else dict(zip(PARAM_NAMES, map(float, params), strict=True)),
        "settling_time": None if info is None else json_number(info.settling_time),
        "overshoot": None if info is None else json_number(info.overshoot),
        "meets": info is not None and not failing_constraints(info, spec),
        "seconds": seconds,
        "seconds_to_spec": to_spec,
        "evaluations": evaluations,
    }


def _comparison(problem, free, n_plants, spec, ours, ours_info, nm, grid_entry) -> dict:
    """The result of :func:`compare_tuners`: the rows, the ratios and the table."""
    result = {
        "problem": problem,
        "free": list(free),
        "plants": n_plants,
        "gradient": _entry(
            params_of(ours.gains),
            ours_info,
            ours.seconds,
            ours.seconds_to_spec,
            ours.iterations * ours.n_starts,
            spec,
        ),
        "nelder_mead": _entry(
            nm["params"], nm["info"], nm["seconds"], nm["first_feasible"], nm["evaluations"], spec
        ),
    }
    result["gradient"]["on_bound"] = sorted(ours.on_bound)
    result["nelder_mead"]["seconds_to_gradient"] = nm["to_gradient"]
    result["nelder_mead"]["stopped"] = nm["stopped"]
    if grid_entry is not None:
        result["grid"] = _entry(*grid_entry, spec)
    result["ratios"] = _ratios(result, nm, ours)
    result["table"] = _compare_table(result)
    return result


def _ratio(a, b):
    try:
        a, b = float(a), float(b)
    except (TypeError, ValueError):
        return None
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else None


def _ratios(result, nm, ours) -> dict:
    """Nelder-Mead's (and the grid's) figures over the gradient tuner's."""
    g = result["gradient"]
    ratios = {
        "settling_nelder_mead_over_gradient": _ratio(
            result["nelder_mead"]["settling_time"], g["settling_time"]
        ),
        "seconds_nelder_mead_over_gradient": _ratio(nm["seconds"], ours.seconds),
        # Nelder-Mead's time to the gradient tuner's worst case, over the gradient's time;
        # where it never got there, its whole run is a lower bound (reported as such).
        "seconds_to_gradient_result_nelder_mead_over_gradient": _ratio(
            nm["to_gradient"] if nm["to_gradient"] is not None else nm["seconds"], ours.seconds
        ),
        "nelder_mead_reached_gradient_result": nm["to_gradient"] is not None,
        "seconds_to_spec_nelder_mead_over_gradient": _ratio(
            nm["first_feasible"], ours.seconds_to_spec
        ),
    }
    if "grid" in result:
        ratios["settling_grid_over_gradient"] = _ratio(
            result["grid"]["settling_time"], g["settling_time"]
        )
    return ratios


def _grid_baseline(
    plants, template, experiment, spec, mask, start_params, log_lo, log_hi, budget, seed
):
    """Best Sobol point of GRID_BOX (the free parameters among kp, kd, ki, tau, kb, v_limit;
    the others at their start) on the batched simulator within ``budget`` seconds, worst over
    ``plants`` where it is a list: (params, exact StepInfo (worst), seconds, seconds to spec,
    points). The hard clip where no force acts, else the tuner's finest smoothing over 4."""
    many = isinstance(plants, list)
    first_plant = plants[0] if many else plants
    friction = has_force_effects(first_plant)
    smoothing = EXACT_FORMS if not friction else LossSettings().smoothing.scaled(SCALES[-1] / 4)
    k = 3 if not mask[3:].any() else len(PARAM_NAMES)  # a row of the gains, or of all six
    names = PARAM_NAMES[:k]
    lo = np.maximum(np.log([GRID_BOX[n][0] for n in names]), log_lo[:k])
    hi = np.minimum(np.log([GRID_BOX[n][1] for n in names]), log_hi[:k])
    sobol = qmc.Sobol(d=k, scramble=True, seed=seed)
    batch = 4096 if not many else 256  # (a point is a run per plant)
    t0 = time.perf_counter()
    n_points, best, first = 0, None, None
    while time.perf_counter() - t0 < budget:
        g = np.exp(lo + sobol.random(batch) * (hi - lo))
        g = np.where(mask[:k], g, start_params[:k])
        info = step_metrics_batch(plants, template, experiment, g, smoothing=smoothing)
        n_points += batch
        ok = (
            (~info.diverged)
            & (info.settling_time < spec.settling_time)
            & (info.overshoot < spec.overshoot)
        )
        if ok.any():
            if first is None:
                first = time.perf_counter() - t0
            i = int(np.argmin(np.where(ok, info.settling_time, np.inf)))
            if best is None or info.settling_time[i] < best[0]:
                best = (float(info.settling_time[i]), g[i])
    seconds = time.perf_counter() - t0
    if best is None:
        return None, None, seconds, first, n_points
    params = np.concatenate([best[1], start_params[k:]])
    pid = controller_with(template, list(params))
    info = worst([exact_info(p, pid, experiment) for p in (plants if many else [plants])])
    return params, info, seconds, first, n_points


def _compare_table(result) -> str:
    def f(x, digits=3):
        return "-" if x is None else (x if isinstance(x, str) else f"{x:.{digits}f}")

    worst = "worst " if result["plants"] > 1 else ""
    lines = [
        f"problem {result['problem']}: free {', '.join(result['free'])}; "
        f"{result['plants']} plant(s), exact simulator",
        f"{'method':<36s}{worst + 'settling [s]':>19s}{worst + 'overshoot [%]':>21s}"
        f"{'meets':>7s}{'wall [s]':>10s}{'to spec [s]':>13s}{'evaluations':>13s}",
    ]
    for key, label in METHODS.items():
        if key not in result:
            continue
        e = result[key]
        lines.append(
            f"{label:<36s}{f(e['settling_time']):>19s}{f(e['overshoot'], 2):>21s}"
            f"{'yes' if e['meets'] else 'no':>7s}{f(e['seconds'], 1):>10s}"
            f"{f(e['seconds_to_spec'], 2):>13s}{e['evaluations']:>13,d}"
        )
    r = result["ratios"]
    nm = result["nelder_mead"]
    reached = (
        f"Nelder-Mead reached the gradient result after {nm['seconds_to_gradient']:.1f} s: "
        f"{f(r['seconds_to_gradient_result_nelder_mead_over_gradient'], 2)}x the gradient's time"
        if r["nelder_mead_reached_gradient_result"]
        else "Nelder-Mead never reached the gradient result (stopped: "
        f"{nm['stopped']}); its whole run is "
        f"{f(r['seconds_to_gradient_result_nelder_mead_over_gradient'], 2)}x the gradient's time"
    )
    lines.append(
        "ratios: settling NM/gradient {}; wall time NM/gradient {}; time to spec NM/gradient "
        "{}".format(
            f(r["settling_nelder_mead_over_gradient"]),
            f(r["seconds_nelder_mead_over_gradient"], 2),
            f(r["seconds_to_spec_nelder_mead_over_gradient"], 2),
        )
    )
    lines.append(reached)
    if "settling_grid_over_gradient" in r:
        lines.append(f"settling grid/gradient {f(r['settling_grid_over_gradient'])}")
    if result["gradient"].get("on_bound"):
        lines.append(
            "note: the gradient result has "
            + ", ".join(result["gradient"]["on_bound"])
            + " on a bound of the search box (both methods search the same box)"
        )
    return "\n".join(lines)


def medians(reports: Sequence[dict]) -> dict:
    """{method: {"seconds_to_spec", "seconds", "settling_time", "reached"}} over several
    :func:`compare_tuners` results (their "table" left out) of one problem: the median of
    each figure over the runs where it exists (a method that never met the spec in a run
    counts its whole run there, a lower bound), and in how many runs it met the spec."""
    out = {}
    for key in METHODS:
        rows = [r[key] for r in reports if key in r]
        if not rows:
            continue
        to_spec = [
            r["seconds_to_spec"] if r["seconds_to_spec"] is not None else r["seconds"] for r in rows
        ]
        settling = [float(r["settling_time"]) for r in rows if r["meets"]]
        out[key] = {
            "seconds_to_spec": statistics.median(to_spec),
            "seconds": statistics.median(r["seconds"] for r in rows),
            "settling_time": statistics.median(settling) if settling else None,
            "reached": sum(r["seconds_to_spec"] is not None for r in rows),
            "runs": len(rows),
        }
    return out


def medians_table(reports: Sequence[dict]) -> str:
    """The medians of several runs of one problem (:func:`medians`), as text."""
    m = medians(reports)
    lines = [
        f"problem {reports[0]['problem']}: medians of {len(reports)} runs (seeds differ); "
        "to spec: until the first parameters meeting it (the whole run where none did)",
        f"{'method':<36s}{'to spec [s]':>13s}{'reached':>9s}{'wall [s]':>10s}{'settling [s]':>14s}",
    ]
    for key, label in METHODS.items():
        if key not in m:
            continue
        e = m[key]
        settling = "-" if e["settling_time"] is None else f"{e['settling_time']:.3f}"
        lines.append(
            f"{label:<36s}{e['seconds_to_spec']:13.2f}{e['reached']:>6d}/{e['runs']:<2d}"
            f"{e['seconds']:10.1f}{settling:>14s}"
        )
    return "\n".join(lines)
