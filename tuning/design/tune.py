"""Gradient PID tuning through the smoothed simulator, every result re-checked on the exact one.

    start parameters --> [multi-start batch, log space] --> adam steps on the smooth loss
                            ^                                  |  (tuning/design/losses.py: summed
                            in
                            |                                  v   the loop, forward mode)
                            '--- project into bounds <--- exact-threshold metrics of the same
                                                          smooth runs -> best so far; widths
                                                          shrink as the parameters settle
    end: best candidates -> exact simulator (jaxcart.exact) -> gains, or the best effort and the
    constraint that fails; every free parameter on a bound of the box is named

One compiled function does a whole iteration (loss, forward-mode gradient with one tangent per
free parameter, adam step, projection, metrics), so a cold run compiles one program. The free
parameters are any of the PID's numbers (:data:`tuning.design.losses.PARAM_NAMES`: kp, kd, ki, tau,
kb, v_limit). The default problem is the lab's: move 0.5 m, settling (2 % band) under 1 s,
overshoot under 5 %, 6 V saturation, handout plant, from the handout's gains kp = 40, kd = 5,
ki = 5. Among gains that meet it, the loss keeps driving the settling time down toward the
physical limit; the tuner stops when no better point appeared for ``patience`` iterations at
the finest width.

>>> res = tune()  # doctest: +SKIP
>>> res.meets, round(res.exact.settling_time, 3), res.on_bound  # doctest: +SKIP
(True, 0.708, {'kp': ('upper', 250.0)})
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from hw.control_law import PID, float_pid
from jaxcart import aot
from jaxcart.errors import UserError
from jaxcart.experiments import step
from jaxcart.metrics import StepInfo
from jaxcart.parallel import batch_sharding, devices, put, replicated
from jaxcart.params import Plant
from jaxcart.plantspec import build_plant, handout_plant
from jaxcart.smooth_sim import EXACT_FORMS
from jaxcart.smoothing import continuation
from tuning.design.losses import (
    GAIN_NAMES,
    PARAM_NAMES,
    LossSettings,
    Spec,
    batched_value_and_jacfwd,
    controller_with,
    gains_from_theta,
    make_loss,
    params_of,
)

#: The handout's suggested starting gains (kp [V/m], kd [V s/m], ki [V/(m s)]).
HANDOUT_START = (40.0, 5.0, 5.0)
#: Default bounds of the gains: kp [V/m], kd [V s/m], ki [V/(m s)]. kp is capped at 250 V/m:
#: beyond it the loop is near bang-bang and gains only ~10 ms of settling on the model (0.715 s
#: at kp ~ 150 against 0.704 s at kp ~ 830, measured), while unmodelled delay and amplifier
#: dynamics make such gains chatter on a real cart. Widen with bounds= / --range.
#: The other parameters: derivative filter tau [s] (0.1 ms to 0.1 s), back-calculation gain kb
#: [1/s] and the software limit v_limit [V] (at most the lab's 6 V amplifier range).
DEFAULT_BOUNDS = {
    "kp": (1e-2, 250.0),
    "kd": (1e-3, 50.0),
    "ki": (1e-3, 200.0),
    "tau": (1e-4, 0.1),
    "kb": (1e-2, 1e3),
    "v_limit": (0.5, 6.0),
}
#: Where a free parameter starts when its start value is 0 (log space needs a positive value).
ZERO_START = {"kp": 1.0, "kd": 0.1, "ki": 0.1, "tau": 1e-3, "kb": 1.0, "v_limit": 6.0}
#: Robust tuning's default plant set: intervals of parameters (M as a fraction of nominal).
DEFAULT_ROBUST = {"B_eq": (3.0, 7.0), "f_c": (0.0, 1.0), "M": (0.9, 1.1)}
#: Continuation: the smoothing widths are multiplied by these factors, stage by stage.
SCALES = continuation(0.125, 4)  # 1, 0.5, 0.25, 0.125


@dataclass
class TuneResult:
    """Outcome of :func:`tune`.

    gains: the tuned controller (every setting); exact / smooth: its metrics on the nominal
    plant from the exact simulator and from the smooth one at the final widths; meets: the
    specification is met on the exact simulator (for robust tuning: on every plant of the
    check set); failing: names of the constraints that fail ("settling_time", "overshoot");
    message: one line saying what happened; history: one dict per iteration (iteration,
    seconds, scale, loss, settling_time [s] and overshoot [%] surrogates of the best start,
    best_settling_time [s] feasible so far on the hard-clip loop); seconds: wall time of the
    call [s] (compilation included); seconds_to_spec: wall time until gains that meet the
    specification were first found [s] (None if never); worst: robust tuning's worst case over
    the check set (exact simulator): a StepInfo whose fields are each the worst over the set;
    plant_set: per plant checked, its parameters and exact metrics; free: the tuned
    parameters; bounds: their search box {name: (lo, hi)}; on_bound: {name: (side, bound)} for
    each free parameter on or within 1 % of a bound (:func:`on_bounds`).
    """

    gains: PID
    exact: StepInfo
    smooth: StepInfo
    meets: bool
    failing: tuple[str, ...]
    message: str
    spec: Spec
    plant: Plant
    history: list = field(default_factory=list)
    seconds: float = 0.0
    seconds_to_spec: float | None = None
    iterations: int = 0
    n_starts: int = 1
    worst: StepInfo | None = None
    plant_set: list | None = None
    free: tuple[str, ...] = GAIN_NAMES
    bounds: dict = field(default_factory=dict)
    on_bound: dict = field(default_factory=dict)

    def bound_note(self, widen: str | None = None) -> str | None:
        """One line naming every free parameter on (or within 1 % of) a bound of the search
        box, and how to widen it (``widen``: the way to say it, default the ``bounds=``
        argument of :func:`tune`); None when there is none."""
        if not self.on_bound:
            return None
        parts = [
            f"{n} = {getattr(self.gains, n):.4g} on its {side} bound {b:g}"
            for n, (side, b) in self.on_bound.items()
        ]
        if widen is None:
            wider = ", ".join(
                f"{n!r}: ({self.bounds[n][0]:g}, {self.bounds[n][1] * 4:g})"
                if side == "upper"
                else f"{n!r}: ({self.bounds[n][0] / 4:g}, {self.bounds[n][1]:g})"
                for n, (side, _) in self.on_bound.items()
            )
            widen = f"bounds={{{wider}}}"
        return (
            "on a bound: " + "; ".join(parts) + f" (the search box limits this result: widen "
            f"it with {widen} to see whether it improves)"
        )

    def as_json(self) -> dict:
        """The ``--json`` document: gains, exact and smooth metrics, wall time [s], ..."""
        keys = ("settling_time", "overshoot", "rise_time", "steady_state_error")
        doc = {
            "gains": self.gains.to_dict(),
            "exact": {k: _num(getattr(self.exact, k)) for k in keys},
            "smooth": {k: _num(getattr(self.smooth, k)) for k in keys},
            "seconds": self.seconds,
            "seconds_to_spec": self.seconds_to_spec,
            "meets": self.meets,
            "failing": list(self.failing),
            "message": self.message,
            "spec": dataclasses.asdict(self.spec),
            "iterations": self.iterations,
            "starts": self.n_starts,
            "free": list(self.free),
            "bounds": {n: list(b) for n, b in self.bounds.items()},
            "on_bound": {
                n: {"side": side, "bound": b, "value": float(getattr(self.gains, n))}
                for n, (side, b) in self.on_bound.items()
            },
            "bound_note": self.bound_note(),
        }
        doc["gains"]["v_limit"] = _num(doc["gains"]["v_limit"])
        if self.worst is not None:
            doc["worst"] = {k: _num(getattr(self.worst, k)) for k in keys}
            doc["plant_set"] = self.plant_set
        return doc


def _num(x):
    x = float(x)
    return x if math.isfinite(x) else ("inf" if x > 0 else "-inf" if x < 0 else "nan")


# ---------------------------------------------------------------- inputs


def _start_and_template(start, controller, free):
    """(start parameters (:data:`PARAM_NAMES` order), controller template) from the user's
    arguments: the template's tau, kb and v_limit unless ``start`` names them."""
    if isinstance(start, PID):
        template = controller or start
        values = dict(zip(PARAM_NAMES, params_of(template), strict=True))
        values.update(zip(GAIN_NAMES, (start.kp, start.kd, start.ki), strict=True))
    else:
        template = controller or PID(tau=0.01, v_limit=6.0, sample_time=0.001)
        values = dict(zip(PARAM_NAMES, params_of(template), strict=True))
        if start is None:  # the handout's start, without the gains that are not free
            values.update(
                (n, g if n in free else 0.0) for n, g in zip(GAIN_NAMES, HANDOUT_START, strict=True)
            )
        elif isinstance(start, Mapping):
            unknown = set(start) - set(PARAM_NAMES)
            if unknown:
                raise UserError(
                    f"start: unknown name(s) {', '.join(sorted(unknown))}; use "
                    f"{', '.join(PARAM_NAMES)}"
                )
            values.update((n, 0.0) for n in GAIN_NAMES)
            values.update((n, float(v)) for n, v in start.items())
        else:
            given = tuple(start)
            if len(given) not in (3, len(PARAM_NAMES)):
                raise UserError(
                    f"start = {start!r}: give three gains kp, kd, ki (or all of "
                    f"{', '.join(PARAM_NAMES)})"
                )
            values.update(zip(PARAM_NAMES, (float(g) for g in given), strict=False))
    for name in PARAM_NAMES:
        g = float(values[name])
        if name == "v_limit" and g == math.inf and name not in free:
            continue  # no software limit: fine while it is not tuned
        if not (math.isfinite(g) and g >= 0):
            what = "gain" if name in GAIN_NAMES else "value"
            raise UserError(f"start {what} {name} = {g!r}: give a finite number >= 0")
    return np.array([float(values[n]) for n in PARAM_NAMES]), template


def _free_mask(free) -> np.ndarray:
    free = tuple(free)
    unknown = [n for n in free if n not in PARAM_NAMES]
    if unknown or not free:
        raise UserError(
            f"free gains {', '.join(free) or '(none)'}: name one or more of "
            f"{', '.join(PARAM_NAMES)}"
        )
    return np.array([n in free for n in PARAM_NAMES])


def _bounds(bounds):
    """(log lower, log upper) bounds in :data:`PARAM_NAMES` order, and the merged dict."""
    merged = dict(DEFAULT_BOUNDS)
    for name, pair in (bounds or {}).items():
        if name not in PARAM_NAMES:
            raise UserError(f"bounds: unknown gain {name!r}; use {', '.join(PARAM_NAMES)}")
        lo, hi = (float(v) for v in pair)
        if not (0 < lo < hi < math.inf):
            raise UserError(f"bounds {name} = ({lo}, {hi}): need 0 < low < high < inf")
        merged[name] = (lo, hi)
    lo = np.log([merged[n][0] for n in PARAM_NAMES])
    hi = np.log([merged[n][1] for n in PARAM_NAMES])
    return lo, hi, merged


def on_bounds(values: Mapping, free: Sequence[str], bounds: Mapping, rel: float = 0.01) -> dict:
    """The free parameters that sit on, or within ``rel`` (1 %) of, a bound: {name: (side,
    bound)} with side "upper" or "lower". Such a result is the box's answer, not the problem's:
    widening that bound may improve it."""
    out = {}
    for name in free:
        lo, hi = bounds[name]
        v = float(values[name])
        if v >= hi * (1 - rel):
            out[name] = ("upper", float(hi))
        elif v <= lo * (1 + rel):
            out[name] = ("lower", float(lo))
    return out


def robust_plants(plant: Plant, ranges=None, *, n_random: int = 0, seed: int = 0):
    """Plants for robust tuning: the corners and centre of the box ``ranges`` ({name: (lo,
    hi)} in SI units; ``M`` as a fraction of the nominal M), plus ``n_random`` uniform samples.

    Returns (plants, values): a list of Plants (all with the same effects, so they stack) and
    the list of {name: value} that made them.
    """
    ranges = dict(DEFAULT_ROBUST if ranges is None else ranges)
    names = sorted(ranges)
    for name in names:
        lo, hi = (float(v) for v in ranges[name])
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise UserError(f"robust range {name} = ({lo}, {hi}): need finite low <= high")
    boxes = np.array([[float(v) for v in ranges[n]] for n in names])
    corners = np.array(np.meshgrid(*boxes, indexing="ij")).reshape(len(names), -1).T
    rows = [boxes.mean(axis=1)] + list(np.unique(corners, axis=0))
    rng = np.random.default_rng(seed)
    rows += list(boxes[:, 0] + rng.random((n_random, len(names))) * np.ptp(boxes, axis=1))
    values = []
    plants = []
    for row in rows:
        v = dict(zip(names, (float(x) for x in row), strict=True))
        if "M" in v:
            v["M"] = v["M"] * float(plant.M)
        values.append(v)
    # Same effect structure for every plant (an effect everywhere if anywhere).
    base = plant
    for name in sorted({n for v in values for n in v} - set(base.param_names())):
        base = build_plant({name: 0.0}, base=base, check=False, where="robust set")
    for v in values:
        try:
            plants.append(build_plant(v, base=base, check=False, where="robust set"))
        except (KeyError, ValueError) as exc:
            raise UserError(f"robust plant set: {exc}") from None
    return plants, values


def _stack(plants: Sequence[Plant]) -> Plant:
    return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x, dtype=float) for x in xs]), *plants)


def _has_friction(plant: Plant) -> bool:
    """True where force effects act (the loop then needs sub-steps and narrow widths)."""
    return bool(plant.stage("force"))


# ---------------------------------------------------------------- exact checks


def exact_info(plant: Plant, controller: PID, experiment) -> StepInfo:
    """Metrics of one run on the exact simulator (:mod:`jaxcart.exact`)."""
    from jaxcart.exact import step_info_exact  # written beside this package: import late

    return step_info_exact(plant, float_pid(controller), experiment)


def _violation(settling, overshoot, spec: Spec) -> float:
    """How far from the specification: max of the normalized metrics (< 1 meets it)."""
    settling = min(float(settling), 10.0 * spec.horizon)
    overshoot = min(float(overshoot), 1e4)
    return max(settling / spec.settling_time, overshoot / spec.overshoot)


def failing_constraints(info: StepInfo, spec: Spec) -> tuple[str, ...]:
    """Names of the constraints ``info`` fails: "settling_time", "overshoot", "diverged"."""
    out = []
    if bool(info.diverged):
        out.append("diverged")
    if not float(info.settling_time) < spec.settling_time:
        out.append("settling_time")
    if not float(info.overshoot) < spec.overshoot:
        out.append("overshoot")
    return tuple(out)


# ---------------------------------------------------------------- the tuner


def tune(
    plant: Plant | None = None,
    *,
    spec: Spec | None = None,
    start=None,
    free: Sequence[str] = GAIN_NAMES,
    controller: PID | None = None,
    robust=False,
    n_starts: int = 8,
    spread: float = 0.5,
    max_iterations: int = 400,
    learning_rate: float = 0.25,
    patience: int = 8,
    stage_iterations: int = 10,
    check_every: int = 1,
    bounds: Mapping | None = None,
    settings: LossSettings | None = None,
    substeps: int | None = None,
    n_check: int = 16,
    seed: int = 0,
    progress: bool | Callable[[dict], None] | None = None,
    processes=None,
) -> TuneResult | None:
    """Tune the canonical PID by gradient descent on the smooth simulator.

    plant: design model (default :func:`jaxcart.handout_plant`: the nominal model, B_eq = 5.4
        kg/s, no effects; the 6 V of the lab is the controller's ``v_limit``; a plant with
        force effects such as Coulomb friction is simulated with sub-steps, slower).
    spec: :class:`tuning.design.losses.Spec` (step 0.5 m, settling < 1 s, overshoot < 5 %).
    start: (kp, kd, ki) [V/m, V s/m, V/(m s)], all six of :data:`PARAM_NAMES`, a {name:
        value} dict or a PID; default the handout's (40, 5, 5) with the gains that are not
        free set to 0, and tau, kb, v_limit from ``controller``. What is not free stays at its
        start value.
    free: the parameters to tune among kp, kd, ki, tau [s], kb [1/s] (back-calculation
        anti-windup) and v_limit [V], e.g. ("kp", "kd") for a PD controller.
    controller: template for the other settings (tau, derivative_on, anti_windup, kb, v_limit,
        sample_time); default tau = 0.01 s, on error, no anti-windup, 6 V, 1 ms.
    robust: False; True for the default plant set (B_eq in [3, 7] kg/s, f_c in [0, 1] N, M
        within +/-10 %); a {name: (lo, hi)} dict (M as a fraction of nominal); or a list of
        Plants. The loss is then the soft maximum over the set (vmapped), and the result is
        checked on the set plus ``n_check`` random plants of the box (a list: on itself).
    n_starts: starts in the vmapped batch: the given one and log-normal perturbations of the
        free parameters (``spread``: standard deviation of their logs); sharded over the
        devices (jaxcart.parallel), padded with copies of the first start to a multiple of
        their number, so the result is the same on any number of devices.
    max_iterations, learning_rate (adam, cosine decay, in log parameter: 0.25 is a 25 % step),
        stage_iterations (most iterations at one smoothing width; fewer once the parameters
        stop moving), patience (iterations at the final width without a better point before
        stopping), check_every (iterations between looks at the exact-threshold metrics of the
        smooth runs, which pick the candidates).
    bounds: {name: (lo, hi)} limits (default :data:`DEFAULT_BOUNDS`).
    settings: :class:`tuning.design.losses.LossSettings` (weights, margins, widths).
    substeps: sub-steps per sample of the smooth simulator (default
        :func:`jaxcart.substeps.substeps_per_sample`: 1 without force effects, 2 with).
    progress: True for a status line on stderr, or a callable receiving each history dict.
    processes: a :class:`tuning.design.tunerun.StartShare` for a jax.distributed run: this process
        iterates its share of the starts and every process sees the whole batch, so the result
        is the single-process one; it is returned on process 0 only (None on the others).
        Inside ``processes.carry()`` (as ``jaxcart tune`` calls it), an exception one process
        meets is raised on every process at its next exchange, none waiting for another.

    Gradients are forward-mode (one tangent per free parameter, the loss summed inside the
    simulation loop) and one compiled function does the whole iteration: loss, gradient, adam
    step, projection and the step metrics that track the best point.

    Never raises for a specification it cannot meet: ``meets`` is False, ``failing`` names the
    constraints and ``message`` says so; the best effort is returned.
    """
    t0 = time.perf_counter()
    p = _problem(
        plant,
        spec=spec or Spec(),
        start=start,
        free=free,
        controller=controller,
        robust=robust,
        bounds=bounds,
        settings=settings or LossSettings(),
        substeps=substeps,
        n_check=n_check,
        seed=seed,
    )
    n_starts = max(1, n_starts)
    theta, rows = _starts(p, n_starts, spread, seed)
    treedef = jax.tree.structure(p.plants_arg)
    update, adam = _compiled(p.template, p.spec, p.settings, p.robust, p.substeps, treedef)
    if processes is not None:  # this process's starts computed, the whole batch returned
        update = processes.wrap(update)
    # The optimizer state lives where the update puts it (else the second step recompiles).
    opt_state = initial_state(adam, theta, rows)
    schedule = _Schedule(max_iterations, learning_rate, patience, stage_iterations, check_every)
    run = _descend(update, p, theta, opt_state, schedule, _progress(progress), t0)
    if processes is not None and not processes.finish():
        return None  # another process of a distributed run: process 0 verifies and reports
    return _conclude(p, update, run, n_starts, t0)


@dataclass
class _Problem:
    """What :func:`tune` was asked, checked and placed: the specification, the controller
    template, the free parameters (names and mask over :data:`PARAM_NAMES`), the start, the
    box (logs ``lo``, ``hi``; ``box`` in units), the plant (or stacked set ``plants_arg``) and
    the plants the result is checked on (robust tuning; else None)."""

    spec: Spec
    settings: LossSettings
    plant: Plant
    template: PID
    free: tuple[str, ...]
    free_mask: np.ndarray
    start_params: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    box: dict
    experiment: object
    plants_arg: Plant
    substeps: int | None
    check_plants: list | None
    check_values: list | None

    @property
    def robust(self) -> bool:
        return self.check_plants is not None


def _problem(
    plant, *, spec, start, free, controller, robust, bounds, settings, substeps, n_check, seed
) -> _Problem:
    """The checked problem of :func:`tune` (a UserError names what is wrong)."""
    plant = handout_plant() if plant is None else plant
    free_mask = _free_mask(free)
    free = tuple(n for n in PARAM_NAMES if n in free)
    start_params, template = _start_and_template(start, controller, free)
    template = float_pid(template)
    if "kb" in free and template.anti_windup != "back_calculation":
        raise UserError(
            "free kb: the back-calculation gain acts only with anti_windup='back_calculation' "
            "(--anti-windup back_calculation)"
        )
    lo, hi, box = _bounds(bounds)
    experiment = step(spec.step, horizon=spec.horizon, sample_time=template.sample_time)
    plants_arg, friction, check_plants, check_values = _plant_set(plant, robust, n_check, seed)
    return _Problem(
        spec=spec,
        settings=settings,
        plant=plant,
        template=template,
        free=free,
        free_mask=free_mask,
        start_params=start_params,
        lo=lo,
        hi=hi,
        box=box,
        experiment=experiment,
        plants_arg=plants_arg,
        substeps=substeps,
        check_plants=check_plants,
        check_values=check_values,
    )


def _plant_set(plant: Plant, robust, n_check: int, seed: int):
    """(plants_arg: the plant on the device or the stacked training set, friction: whether
    force effects act, check_plants, check_values: the set the result is checked on and its
    parameters, None without robust tuning)."""
    if robust is False or robust is None:
        # On the device once (a Python number is transferred again at every call).
        return jax.tree.map(put, plant), _has_friction(plant), None, None
    if isinstance(robust, Sequence) and all(isinstance(p, Plant) for p in robust):
        train = list(robust)
        if not train or len({jax.tree.structure(p) for p in train}) != 1:
            raise UserError(
                "robust plant list: give one or more plants with the same effects (add "
                "Coulomb(0.0) where a plant has no friction)"
            )
        check_values = [
            {n: float(p.get(n)) for n in ("M", "B_eq", "f_c") if n in p.param_names()}
            for p in train
        ]
        check_plants = train
    else:
        ranges = None if robust is True else robust
        train, _ = robust_plants(plant, ranges)
        check_plants, check_values = robust_plants(plant, ranges, n_random=n_check, seed=seed + 1)
    friction = any(_has_friction(p) for p in train)
    return _stack(train), friction, check_plants, check_values


def _starts(p: _Problem, n_starts: int, spread: float, seed: int):
    """(theta, rows): the logs of the starts, on the devices, and their placement. The given
    start, then log-normal perturbations of the free parameters (``spread``: standard
    deviation of their logs), clipped into the box."""
    free_mask, start_params = p.free_mask, p.start_params
    base = np.where(
        free_mask & (start_params <= 0), [ZERO_START[n] for n in PARAM_NAMES], start_params
    )
    theta0 = np.log(np.where(free_mask, base, 1.0))
    rng = np.random.default_rng(seed)
    noise = spread * rng.standard_normal((n_starts - 1, len(PARAM_NAMES)))
    theta = np.concatenate([theta0[None], theta0[None] + noise]) * free_mask
    theta = np.clip(theta, p.lo, p.hi) * free_mask
    # The batch of starts is sharded over every device: pad it to a multiple with copies of the
    # first start (never new random ones), so the result does not depend on the device count.
    n_dev = len(devices())
    theta = np.concatenate([theta, np.repeat(theta[:1], -n_starts % n_dev, axis=0)])
    # One device: the placement the compiled update returns (a second signature otherwise).
    rows = batch_sharding() if n_dev > 1 else replicated()
    return put(theta, float, rows), rows


class _Schedule(NamedTuple):
    """The iterations of :func:`tune` (see its arguments)."""

    max_iterations: int
    learning_rate: float
    patience: int
    stage_iterations: int
    check_every: int


@dataclass
class _Candidates:
    """The step metrics (exact thresholds) of every start's smooth run: the candidates for
    the exact check and the best point so far.

    found: rounded params -> (key, params, settling [s], overshoot [%], scale); key: the
    best (settling, overshoot), or (inf, violation) while nothing meets the specification;
    improved_at: the last iteration the settling time improved by half a sample or more;
    seconds_to_spec: when a point first met the specification [s]."""

    spec: Spec
    t0: float
    found: dict = field(default_factory=dict)
    key: tuple = (math.inf, math.inf)
    improved_at: int | None = None
    seconds_to_spec: float | None = None

    def record(self, params, metrics, it: int, scale: float, ts: float) -> None:
        spec = self.spec
        settle, over = np.asarray(metrics.settling_time), np.asarray(metrics.overshoot)
        bad = np.asarray(metrics.diverged)
        for g, s, o, b in zip(np.asarray(params), settle, over, bad, strict=True):
            feasible = (not b) and s < spec.settling_time and o < spec.overshoot
            key = (s, o) if feasible else (math.inf, _violation(s, o, spec))
            # The finest widths rank first among equals: they are closest to the exact loop.
            self.found[tuple(float(f"{x:.5g}") for x in g)] = (key, g, s, o, scale)
            if key < self.key:
                # Progress is half a sample or more of settling time (or the first feasible).
                if feasible and key[0] < self.key[0] - 0.5 * ts:
                    self.improved_at = it
                if feasible and self.seconds_to_spec is None:
                    self.seconds_to_spec = time.perf_counter() - self.t0
                self.key = key


@dataclass
class _Run:
    """Where :func:`_descend` ended: the last iterate (logs), the optimizer state, the
    candidates, the history (one dict per iteration), the iterations done, and the update's
    arguments that stay on the devices (the free parameters' indices, the box's logs)."""

    theta: object
    opt_state: object
    candidates: _Candidates
    history: list
    iterations: int
    free_idx: object
    box: tuple


def _descend(update, p: _Problem, theta, opt_state, schedule: _Schedule, report, t0) -> _Run:
    """The adam iterations over the batch of starts, with the continuation of the smoothing
    widths (:data:`SCALES`) and the early stop."""
    ts = p.template.sample_time
    free_idx = put(np.flatnonzero(p.free_mask), np.int32)
    fixed = put(np.where(np.isfinite(p.start_params), p.start_params, 1e30), float)
    mask = put(p.free_mask)
    lo_j, hi_j = put(np.asarray(p.lo)[None], float), put(np.asarray(p.hi)[None], float)
    candidates = _Candidates(p.spec, t0)
    history: list[dict] = []
    stage = _Stage(np.asarray(theta))
    it = 0
    for it in range(schedule.max_iterations):  # noqa: B007 (it is used after the loop)
        scale = put(SCALES[stage.index], theta.dtype)
        lr = _cosine(schedule.learning_rate, it, schedule.max_iterations)
        params, theta, opt_state, values_now, info, metrics = update(
            theta, opt_state, lr, free_idx, fixed, mask, p.plants_arg, scale, lo_j, hi_j
        )
        if it % schedule.check_every == 0:
            candidates.record(params, metrics, it, SCALES[stage.index], ts)
        entry = _history_entry(it, t0, scale, values_now, info, candidates.key)
        history.append(entry)
        report(entry)
        stage.advance(it, theta, schedule.stage_iterations)
        if stage.finished(it, schedule.patience, candidates.improved_at):
            break
    report(None)
    return _Run(theta, opt_state, candidates, history, it + 1, free_idx, (lo_j, hi_j))


def _history_entry(it, t0, scale, values_now, info, best_key) -> dict:
    """One iteration's history: its loss, the settling time and overshoot surrogates of the
    best start, the best settling time that meets the specification so far."""
    values_np = np.asarray(values_now)
    j = int(np.argmin(values_np))
    return {
        "iteration": it,
        "seconds": time.perf_counter() - t0,
        "scale": float(scale),
        "loss": float(values_np[j]),
        "settling_time": float(np.max(np.asarray(info.settling_time)[j])),
        "overshoot": float(np.max(np.asarray(info.overshoot)[j])),
        "best_settling_time": float(best_key[0]),
    }


class _Stage:
    """The continuation: the stage (index into :data:`SCALES`) of the smoothing widths, the
    iteration it began and the parameters 5 iterations ago."""

    def __init__(self, anchor):
        self.index, self.start, self.anchor = 0, 0, anchor

    def advance(self, it: int, theta, stage_iterations: int) -> None:
        """Shrink the widths once the parameters stop moving at this width."""
        done_in_stage = it + 1 - self.start
        if done_in_stage % 5 == 0:
            moved = float(np.max(np.abs(np.asarray(theta) - self.anchor)))  # over 5 iterations
            last = self.index + 1 >= len(SCALES)
            if not last and (moved < 0.02 or done_in_stage >= stage_iterations):
                self.index, self.start = self.index + 1, it + 1
            self.anchor = np.asarray(theta)

    def finished(self, it: int, patience: int, improved_at: int | None) -> bool:
        """Early stop: finest width and no better point for ``patience`` iterations."""
        if self.index == len(SCALES) - 1 and it - self.start >= patience:
            last = improved_at if improved_at is not None else self.start
            return it - max(last, self.start) >= patience
        return False


def _conclude(p: _Problem, update, run: _Run, n_starts: int, t0: float) -> TuneResult:
    """The best candidates checked on the exact simulator, and the :class:`TuneResult`."""
    chosen, exact, checked = _verify(
        run.candidates.found, p.template, p.plant, p.experiment, p.spec, p.check_plants
    )
    gains = float_pid(controller_with(float_pid(p.template), [float(x) for x in chosen]))
    smooth = _smooth_report(
        update,
        run.opt_state,
        gains,
        p.plant,
        p.plants_arg,
        p.robust,
        run.theta,
        run.free_idx,
        run.box,
    )
    worst = plant_set = None
    judged = exact
    if p.robust:
        worst = judged = _worst(checked)
        plant_set = [
            {"params": v, "exact": _info_dict(i)}
            for v, i in zip(p.check_values, checked, strict=True)
        ]
    failing = failing_constraints(judged, p.spec)
    meets = not failing
    seconds_to_spec = run.candidates.seconds_to_spec
    if meets and seconds_to_spec is None:
        seconds_to_spec = time.perf_counter() - t0
    values = dict(zip(PARAM_NAMES, params_of(gains), strict=True))
    return TuneResult(
        gains=gains,
        exact=exact,
        smooth=smooth,
        meets=meets,
        failing=failing,
        message=_message(meets, failing, judged, p.spec, p.robust, len(p.check_plants or [])),
        spec=p.spec,
        plant=p.plant,
        history=run.history,
        seconds=time.perf_counter() - t0,
        seconds_to_spec=seconds_to_spec if meets else None,
        iterations=run.iterations,
        n_starts=n_starts,
        worst=worst,
        plant_set=plant_set,
        free=p.free,
        bounds={n: p.box[n] for n in p.free},
        on_bound=on_bounds(values, p.free, p.box),
    )


#: Compiled iteration functions, by static configuration: a second tune() with other starts,
#: bounds or free parameters (as many, same batch size) compiles nothing.
_CACHE: dict = {}


def _compiled(template, spec, settings, robust, substeps, treedef):
    """(update, adam) for a static configuration, jitted once.

    update(theta, opt_state, lr, free, fixed, mask, plants, scale, lo, hi) -> (params, theta,
        opt_state, per-start losses, LossInfo, StepInfo): the parameters at ``theta``, one adam
        step (lr [log parameter]) on the batch of starts projected into [lo, hi] (logs), the
        loss, its smooth metrics and the exact-threshold step metrics of the same smooth runs
        (robust: the worst over the plants), all from one forward-mode pass.
    One compiled function, not a chain of small eager operations or a second checking
    program: each distinct program costs seconds of first-call compilation.
    """
    key = (template, spec, settings, robust, substeps, treedef)
    if key not in _CACHE:
        experiment = step(spec.step, horizon=spec.horizon, sample_time=template.sample_time)
        loss = make_loss(template, experiment, spec, settings, robust=robust, substeps=substeps)
        value_and_grad = batched_value_and_jacfwd(loss)
        adam = optax.scale_by_adam()

        def update(theta, opt_state, lr, free, fixed, mask, plants, scale, lo, hi):
            values, aux, grad = value_and_grad(theta, free, fixed, mask, plants, scale)
            info = aux[1] if robust else aux
            metrics = info.metrics
            if robust:  # field-wise worst over the plants (axis 1)
                metrics = StepInfo(
                    *(
                        jnp.any(x, axis=1) if name == "diverged" else jnp.max(x, axis=1)
                        for name, x in zip(StepInfo._fields, metrics, strict=True)
                    )
                )
            grad = jnp.where(jnp.isfinite(grad), grad, 0.0)  # a blown-up run teaches nothing
            direction, opt_state = adam.update(grad, opt_state, theta)
            params = gains_from_theta(theta, fixed[None], mask[None])
            theta = jnp.clip(theta - lr * direction, lo, hi) * mask[None]
            return params, theta, opt_state, values, info, metrics

        _CACHE[key] = (aot.jit(update, "tune-update", key), adam)
    return _CACHE[key]


def initial_state(adam, theta, rows):
    """``adam.init(theta)`` built on the host and placed where the update puts it (``rows``
    for the per-start moments, a copy on every device for the step count): ``init``'s eager
    zeros compile a small program per shape in every new process. optax's adam state is all
    zeros (a test compares this with ``adam.init``)."""
    return jax.tree.map(
        lambda x: put(np.zeros(x.shape, x.dtype), None, rows if x.ndim == 2 else replicated()),
        jax.eval_shape(adam.init, theta),
    )


def _smooth_report(update, state, gains, plant, plants_arg, robust, theta, free_idx, box):
    """StepInfo of ``gains`` on ``plant``, smooth loop at the finest width of the continuation,
    through the compiled update (every row the fixed ``gains``, same shapes: nothing new to
    compile; for robust tuning every plant of the stack is the nominal one)."""
    fixed = put(params_of(gains), float)
    mask = put(np.zeros(len(PARAM_NAMES), dtype=bool))  # every row: the fixed parameters
    if robust:
        # The nominal plant with the set's effects (friction included even where f_c = 0).
        values = {n: float(plant.get(n)) for n in ("M", "B_eq") if n in plant.param_names()}
        values["f_c"] = float(plant.get("f_c")) if "f_c" in plant.param_names() else 0.0
        nominal = build_plant(values, base=plant, check=False, where="robust set")
        n_plants = jax.tree.leaves(plants_arg)[0].shape[0]
        one = jax.tree.map(lambda x: x[0], plants_arg)
        if jax.tree.structure(nominal) != jax.tree.structure(one):
            nominal = plant
        plants_arg = _stack([nominal] * n_plants)
    else:
        plants_arg = jax.tree.map(put, plant)
    scale = put(SCALES[-1], theta.dtype)
    out = update(theta, state, 0.0, free_idx, fixed, mask, plants_arg, scale, *box)
    info = out[4]
    metrics = info.metrics
    if robust:
        metrics = StepInfo(*(np.asarray(x)[:, 0] for x in metrics))
    return StepInfo(*(np.asarray(x)[0].item() for x in metrics))


def _cosine(lr0: float, k: int, n: int, alpha: float = 0.1) -> float:
    """Learning rate at iteration k of n: cosine decay from lr0 to alpha lr0 (optax's form)."""
    return lr0 * ((1 - alpha) * 0.5 * (1 + math.cos(math.pi * min(k, n) / n)) + alpha)


def _verify(candidates, template, plant, experiment, spec, check_plants, tries=None):
    """Best of the leading candidates on the exact simulator; else the one closest to spec.

    The candidates were ranked by the smooth runs, which differ a little from the exact loop
    (most at wide smoothing), so the leading ``tries`` (default 6 for one plant, 3 for a set)
    are all checked and the best exact result wins. Returns (parameters, exact StepInfo on
    ``plant``, per-plant exact StepInfos or None).
    """
    tries = tries or (6 if check_plants is None else 3)
    ranked = sorted(candidates.values(), key=lambda c: (c[0], c[4]))
    best = None
    for _key, g, _s, _o, _scale in ranked[:tries]:
        pid = controller_with(float_pid(template), [float(x) for x in g])
        if check_plants is None:
            info = exact_info(plant, pid, experiment)
            judged, per_plant = info, None
        else:
            per_plant = [exact_info(p, pid, experiment) for p in check_plants]
            judged = _worst(per_plant)
            info = exact_info(plant, pid, experiment)
        ok = not failing_constraints(judged, spec)
        score = (
            0 if ok else 1,
            float(judged.settling_time) if ok else 0.0,
            _violation(judged.settling_time, judged.overshoot, spec),
        )
        if best is None or score < best[0]:
            best = (score, g, info, per_plant)
    _, g, info, per_plant = best
    return g, info, per_plant


def _worst(infos: Sequence[StepInfo]) -> StepInfo:
    """Field-wise worst of several StepInfos (max of every metric, any diverged)."""
    arr = {k: [getattr(i, k) for i in infos] for k in StepInfo._fields}
    return StepInfo(
        **{k: (any(v) if k == "diverged" else float(np.max(v))) for k, v in arr.items()}
    )


def _info_dict(info: StepInfo) -> dict:
    return {k: (bool(v) if k == "diverged" else _num(v)) for k, v in info._asdict().items()}


def _message(meets, failing, info, spec, robust, n_plants) -> str:
    where = f"on all {n_plants} plants of the set (worst case)" if robust else "exact simulator"
    got = f"settling {info.settling_time:.3f} s, overshoot {info.overshoot:.2f} %"
    if meets:
        return (
            f"meets the specification ({where}): {got} "
            f"(bounds {spec.settling_time:g} s, {spec.overshoot:g} %)"
        )
    parts = []
    for name in failing:
        if name == "settling_time":
            parts.append(
                f"settling time {info.settling_time:.3f} s is not under {spec.settling_time:g} s"
            )
        elif name == "overshoot":
            parts.append(f"overshoot {info.overshoot:.2f} % is not under {spec.overshoot:g} %")
        else:
            parts.append("the loop diverges")
    return f"cannot meet the specification ({where}): " + "; ".join(parts) + f". Best found: {got}"


def _progress(progress):
    if callable(progress):
        return lambda entry: entry is not None and progress(entry)
    if not progress:
        return lambda entry: None
    stream = sys.stderr
    tty = stream.isatty()
    state = {"last": -1.0}

    def report(entry):
        if entry is None:
            if tty:
                print(file=stream, flush=True)
            return
        now = entry["seconds"]
        if tty and now - state["last"] < 0.1:
            return
        if not tty and now - state["last"] < 2.0:
            return
        state["last"] = now
        best = entry["best_settling_time"]
        best_text = f"{best:.3f} s" if math.isfinite(best) else "none yet"
        text = (
            f"tune: it {entry['iteration']:4d}  width x{entry['scale']:.3f}  "
            f"loss {entry['loss']:.4f}  smooth settling {entry['settling_time']:.3f} s  "
            f"overshoot {entry['overshoot']:.2f} %  best meeting spec {best_text}  "
            f"{now:.1f} s"
        )
        print(("\r" if tty else "") + text, end="" if tty else "\n", file=stream, flush=True)

    return report


# ---------------------------------------------------------------- benchmark

#: Box of the grid baseline [V/m, V s/m, V/(m s)], sampled log-uniformly: generous around the
#: handout's gains, without the useless corners of DEFAULT_BOUNDS.
GRID_BOX = {"kp": (10.0, 1000.0), "kd": (0.5, 50.0), "ki": (0.01, 50.0)}


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
#: anti-windup, v_limit) robust over the box's centre and corners (9 plants).
PROBLEMS = ("lab", "robust", "wide")
#: Most Nelder-Mead evaluations per problem (each one is a run per plant on the exact
#: simulator), and the most seconds it may take.
NM_EVALUATIONS = {"lab": 600, "robust": 400, "wide": 600}
NM_SECONDS = 600.0


def compare_problem(problem: str, plant: Plant | None = None, *, seed: int = 0):
    """(free, controller, robust, n_check, plants, starts) of a benchmark problem of
    :data:`PROBLEMS` on ``plant`` (default the handout's): ``robust`` and ``n_check`` as
    :func:`tune` takes them (False for the lab problem), ``plants`` the set every result is
    judged on (None: the plant alone), the same set tune checks on."""
    plant = handout_plant() if plant is None else plant
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
        problem, plant, seed=seed
    )
    free = tuple(free or p_free)
    free_mask = _free_mask(free)
    start_params, template = _start_and_template(start, controller or p_controller, free)
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
    log_lo, log_hi, _ = _bounds(bounds)

    # 2. Nelder-Mead on the exact simulator, penalty objective, same start.
    say(f"compare ({problem}): Nelder-Mead on the exact simulator, {len(check)} plant(s) ...")
    nm = _nelder_mead(
        _NelderMeadProblem(template, experiment, spec, check, free_mask, start_params),
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
    if (problem == "lab") if grid is None else grid:
        say(f"compare ({problem}): grid of equal wall time ({ours.seconds:.1f} s) ...")
        grid_entry = _grid_baseline(
            plant,
            template,
            experiment,
            spec,
            free_mask,
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
    from scipy.optimize import minimize

    spec, free_mask = nmp.spec, nmp.free_mask
    log_lo, log_hi = log_box
    base = np.where(
        free_mask & (nmp.start_params <= 0), [ZERO_START[n] for n in PARAM_NAMES], nmp.start_params
    )
    nm = {"evaluations": 0, "best": None, "first_feasible": None, "to_gradient": None}
    t0 = time.perf_counter()

    def objective(x):
        if time.perf_counter() - t0 > max_seconds:
            raise _Done
        g = base.copy()
        # Projected into the tuner's box, so both search the same parameters.
        g[free_mask] = np.exp(np.clip(x, log_lo[free_mask], log_hi[free_mask]))
        pid = controller_with(nmp.template, list(g))
        info = _worst([exact_info(p, pid, nmp.experiment) for p in nmp.plants])
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
            else _violation(info.settling_time, info.overshoot, spec),
        )
        if nm["best"] is None or key < nm["best"][0]:
            nm["best"] = (key, g.copy(), info)
        return penalty_objective(info.settling_time, info.overshoot, info.steady_state_error, spec)

    x0 = np.log(base[free_mask])
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
        "settling_time": None if info is None else _num(info.settling_time),
        "overshoot": None if info is None else _num(info.overshoot),
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
    plant, template, experiment, spec, free_mask, start_params, log_lo, log_hi, budget, seed
):
    """Best Sobol point of GRID_BOX (kp, kd, ki) on the batched hard-clip simulator within
    ``budget`` seconds: (params, exact StepInfo, seconds, seconds to spec, points)."""
    from scipy.stats import qmc

    from jaxcart.batch_metrics import step_metrics_batch

    friction = _has_friction(plant)
    smoothing = EXACT_FORMS if not friction else LossSettings().smoothing.scaled(SCALES[-1] / 4)
    gain_mask = free_mask[:3]
    lo = np.maximum(np.log([GRID_BOX[n][0] for n in GAIN_NAMES]), log_lo[:3])
    hi = np.minimum(np.log([GRID_BOX[n][1] for n in GAIN_NAMES]), log_hi[:3])
    sobol = qmc.Sobol(d=3, scramble=True, seed=seed)
    batch = 4096
    t0 = time.perf_counter()
    n_points, best, first = 0, None, None
    while time.perf_counter() - t0 < budget:
        g = np.exp(lo + sobol.random(batch) * (hi - lo))
        g = np.where(gain_mask, g, start_params[:3])
        info = step_metrics_batch(plant, template, experiment, g, smoothing=smoothing)
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
    params = np.concatenate([best[1], start_params[3:]])
    info = exact_info(plant, controller_with(template, list(params)), experiment)
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
    names = {
        "gradient": "gradient (this tuner, exact check)",
        "nelder_mead": "scipy Nelder-Mead, exact simulator",
        "grid": "Sobol grid, equal wall time",
    }
    for key, label in names.items():
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


__all__ = [
    "tune",
    "TuneResult",
    "Spec",
    "LossSettings",
    "robust_plants",
    "exact_info",
    "failing_constraints",
    "compare_tuners",
    "compare_problem",
    "on_bounds",
    "PROBLEMS",
    "penalty_objective",
    "HANDOUT_START",
    "DEFAULT_BOUNDS",
    "DEFAULT_ROBUST",
    "GRID_BOX",
]
