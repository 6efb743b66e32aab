"""Gradient PID tuning through the smoothed simulator, every result re-checked on the exact one.

    start gains --> [multi-start batch, log space] --> adam steps on the smooth loss
                        ^                                   |  (tuning/losses.py; continuation:
                        |                                   v   widths shrink as gains settle)
                        '--- project into bounds <--- every few steps: metrics of every start on
                                                      the hard-clip loop -> best feasible so far
    end: best candidates -> exact simulator (jaxcart.exact) -> gains, or the best effort and the
    constraint that fails

The default problem is the lab's: move 0.5 m, settling (2 % band) under 1 s, overshoot under
5 %, 6 V saturation, handout plant, from the handout's gains kp = 40, kd = 5, ki = 5. Among gains
that meet it, the loss keeps driving the settling time down toward the physical limit.

>>> res = tune(max_iterations=60, n_starts=4)  # about 5 s on 2 cores  # doctest: +SKIP
>>> res.meets, round(res.exact.settling_time, 3)  # doctest: +SKIP
(True, 0.707)
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from hw.control_law import PID, float_pid
from jaxcart.errors import UserError
from jaxcart.experiments import step
from jaxcart.metrics import StepInfo, step_metrics
from jaxcart.params import Plant, handout_plant, voltage_limit
from jaxcart.plantspec import with_values
from jaxcart.smooth import EXACT_FORMS
from jaxcart.smoothing import continuation
from tuning.losses import (
    GAIN_NAMES,
    LossSettings,
    Spec,
    batched_value_and_grad,
    controller_with,
    gains_from_theta,
    make_loss,
)

#: The handout's suggested starting gains (kp [V/m], kd [V s/m], ki [V/(m s)]).
HANDOUT_START = (40.0, 5.0, 5.0)
#: Default bounds of the gains: kp [V/m], kd [V s/m], ki [V/(m s)]. kp is capped at 250 V/m:
#: beyond it the loop is near bang-bang and gains only ~10 ms of settling on the model (0.715 s
#: at kp ~ 150 against 0.704 s at kp ~ 830, measured), while unmodelled delay and amplifier
#: dynamics make such gains chatter on a real cart. Widen with bounds= / --range.
DEFAULT_BOUNDS = {"kp": (1e-2, 250.0), "kd": (1e-3, 50.0), "ki": (1e-3, 200.0)}
#: Where a free gain starts when its start value is 0 (log space needs a positive value).
ZERO_START = {"kp": 1.0, "kd": 0.1, "ki": 0.1}
#: Robust tuning's default plant set: intervals of parameters (M as a fraction of nominal).
DEFAULT_ROBUST = {"B_eq": (3.0, 7.0), "f_c": (0.0, 1.0), "M": (0.9, 1.1)}
#: Sub-steps per sample of the smooth simulator where friction acts, in tuning: measured on the
#: handout plant with f_c = 0.5 to 1 N, 2 sub-steps give the same settling time (to 1 ms) and
#: overshoot (to 0.01 %) as the simulator's default 10, at 2.5x the speed.
FRICTION_SUBSTEPS = 2
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
    plant_set: per plant checked, its parameters and exact metrics.
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
    """(start gains array (kp, kd, ki), controller template) from the user's arguments."""
    if isinstance(start, PID):
        template = controller or start
        gains = (start.kp, start.kd, start.ki)
    else:
        template = controller or PID(tau=0.01, v_limit=6.0, sample_time=0.001)
        if start is None:  # the handout's start, without the terms that are not free
            gains = tuple(
                g if n in free else 0.0 for n, g in zip(GAIN_NAMES, HANDOUT_START, strict=True)
            )
        elif isinstance(start, Mapping):
            unknown = set(start) - set(GAIN_NAMES)
            if unknown:
                raise UserError(
                    f"start gains: unknown name(s) {', '.join(sorted(unknown))}; use kp, kd, ki"
                )
            gains = tuple(float(start.get(n, 0.0)) for n in GAIN_NAMES)
        else:
            gains = tuple(start)
            if len(gains) != 3:
                raise UserError(f"start = {start!r}: give three gains kp, kd, ki")
    gains = tuple(float(g) for g in gains)
    for name, g in zip(GAIN_NAMES, gains, strict=True):
        if not (math.isfinite(g) and g >= 0):
            raise UserError(f"start gain {name} = {g!r}: give a finite number >= 0")
    return np.array(gains), template


def _free_mask(free) -> np.ndarray:
    free = tuple(free)
    unknown = [n for n in free if n not in GAIN_NAMES]
    if unknown or not free:
        raise UserError(f"free gains {', '.join(free) or '(none)'}: name one or more of kp, kd, ki")
    return np.array([n in free for n in GAIN_NAMES])


def _bounds(bounds):
    merged = dict(DEFAULT_BOUNDS)
    for name, pair in (bounds or {}).items():
        if name not in GAIN_NAMES:
            raise UserError(f"bounds: unknown gain {name!r}; use kp, kd, ki")
        lo, hi = (float(v) for v in pair)
        if not (0 < lo < hi < math.inf):
            raise UserError(f"bounds {name} = ({lo}, {hi}): need 0 < low < high < inf")
        merged[name] = (lo, hi)
    lo = np.log([merged[n][0] for n in GAIN_NAMES])
    hi = np.log([merged[n][1] for n in GAIN_NAMES])
    return lo, hi


def _with_params(plant: Plant, values: Mapping) -> Plant:
    """``plant`` with named parameters set through the plant spec (a name of an effect the
    plant lacks adds it: ``f_c`` adds Coulomb friction)."""
    return with_values(plant, {k: float(v) for k, v in dict(values).items()}, where="robust set")


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
        base = _with_params(base, {name: 0.0})
    for v in values:
        try:
            plants.append(_with_params(base, v))
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
    patience: int = 20,
    stage_iterations: int = 30,
    check_every: int = 5,
    bounds: Mapping | None = None,
    settings: LossSettings | None = None,
    substeps: int | None = None,
    n_check: int = 16,
    seed: int = 0,
    progress: bool | Callable[[dict], None] | None = None,
) -> TuneResult:
    """Tune the canonical PID's gains by gradient descent on the smooth simulator.

    plant: design model (default :func:`jaxcart.handout_plant`: the nominal model, B_eq = 5.4
        kg/s, no effects; the 6 V of the lab is the controller's ``v_limit``; a plant with
        force effects such as Coulomb friction is simulated with sub-steps, slower).
    spec: :class:`tuning.losses.Spec` (step 0.5 m, settling < 1 s, overshoot < 5 %).
    start: (kp, kd, ki) [V/m, V s/m, V/(m s)], a {name: gain} dict or a PID; default the
        handout's (40, 5, 5) with the gains that are not free set to 0. Gains not in ``free``
        stay at their start value.
    free: the gains to tune, e.g. ("kp", "kd") for a PD controller.
    controller: template for the other settings (tau, derivative_on, anti_windup, v_limit,
        sample_time); default tau = 0.01 s, on error, no anti-windup, 6 V, 1 ms.
    robust: False; True for the default plant set (B_eq in [3, 7] kg/s, f_c in [0, 1] N, M
        within +/-10 %); a {name: (lo, hi)} dict (M as a fraction of nominal); or a list of
        Plants. The loss is then the soft maximum over the set (vmapped), and the result is
        checked on the set plus ``n_check`` random plants of the box.
    n_starts: starts in the vmapped batch: the given one and log-normal perturbations of the
        free gains (``spread``: standard deviation of log gain); rounded up to a multiple of
        the number of JAX devices, over which the batch is sharded.
    max_iterations, learning_rate (adam, cosine decay, in log gain: 0.25 is a 25 % step),
        stage_iterations (most iterations at one smoothing width; fewer once the gains stop
        moving), patience (iterations at the final width without a better feasible point
        before stopping), check_every (iterations between checks on the hard-clip loop).
    bounds: {name: (lo, hi)} limits of the gains (default :data:`DEFAULT_BOUNDS`).
    settings: :class:`tuning.losses.LossSettings` (weights, margins, widths).
    substeps: sub-steps per sample of the smooth simulator (default 1 without friction,
        :data:`FRICTION_SUBSTEPS` with it).
    progress: True for a status line on stderr, or a callable receiving each history dict.

    Never raises for a specification it cannot meet: ``meets`` is False, ``failing`` names the
    constraints and ``message`` says so; the best effort is returned.
    """
    t0 = time.perf_counter()
    spec = spec or Spec()
    settings = settings or LossSettings()
    plant = handout_plant() if plant is None else plant
    free_mask = _free_mask(free)
    start_gains, template = _start_and_template(start, controller, free)
    template = float_pid(template)
    lo, hi = _bounds(bounds)
    experiment = step(spec.step, horizon=spec.horizon, sample_time=template.sample_time)
    ts = template.sample_time

    # The plant set (robust) or the plant.
    check_plants = check_values = None
    if robust is not False and robust is not None:
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
            check_plants, check_values = robust_plants(
                plant, ranges, n_random=n_check, seed=seed + 1
            )
        plants_arg = _stack(train)
        friction = any(_has_friction(p) for p in train)
    else:
        plants_arg = plant
        friction = _has_friction(plant)
    is_robust = check_plants is not None

    # Starts: the given one, then log-normal perturbations of the free gains.
    base = np.where(
        free_mask & (start_gains <= 0), [ZERO_START[n] for n in GAIN_NAMES], start_gains
    )
    theta0 = np.log(np.where(free_mask, base, 1.0))
    rng = np.random.default_rng(seed)
    # The batch of starts is sharded over every JAX device: round it up to a multiple.
    devices = jax.devices()
    n_starts = -(-max(1, n_starts) // len(devices)) * len(devices)
    noise = spread * rng.standard_normal((n_starts - 1, 3))
    theta = np.concatenate([theta0[None], theta0[None] + noise]) * free_mask
    theta = np.clip(theta, lo, hi) * free_mask
    mesh = Mesh(np.array(devices), ("starts",))
    sharding = NamedSharding(mesh, PartitionSpec("starts"))
    theta = jax.device_put(jnp.asarray(theta), sharding)
    fixed = jnp.asarray(start_gains)
    mask = jnp.asarray(free_mask)

    if substeps is None and friction:
        substeps = FRICTION_SUBSTEPS
    update, check, adam = _compiled(
        template, spec, settings, is_robust, substeps, jax.tree.structure(plants_arg)
    )
    # Tracking: the hard-clip loop (the exact model without friction); with friction, the
    # smooth loop at a quarter of the finest width (the exact simulator has the last word).
    zero = jnp.zeros(())
    tracking = jax.tree.map(
        lambda w: zero + w,
        settings.smoothing.scaled(SCALES[-1] / 4) if friction else settings.smoothing.scaled(0.0),
    )
    # The optimizer state lives where the update puts it (else the second step recompiles).
    replicated = NamedSharding(mesh, PartitionSpec())
    opt_state = jax.tree.map(
        lambda x: jax.device_put(x, sharding if x.ndim == 2 else replicated), adam.init(theta)
    )
    lo_j, hi_j = jnp.asarray(lo)[None], jnp.asarray(hi)[None]

    report = _progress(progress)
    history: list[dict] = []
    candidates: dict[tuple, tuple] = {}  # rounded gains -> (key, gains, settling, overshoot)
    best = {"key": (math.inf, math.inf), "improved_at": None, "seconds_to_spec": None}

    def record(theta, it):
        """Metrics of every start on the tracking loop; keep them as candidates."""
        gains_now, info_now = check(theta, fixed, mask, plants_arg, tracking)
        gains_now = np.asarray(gains_now)
        settle, over = np.asarray(info_now.settling_time), np.asarray(info_now.overshoot)
        for g, s, o in zip(gains_now, settle, over, strict=True):
            feasible = s < spec.settling_time and o < spec.overshoot
            key = (s, o) if feasible else (math.inf, _violation(s, o, spec))
            candidates[tuple(float(f"{x:.5g}") for x in g)] = (key, g, s, o)
            if key < best["key"]:
                # Progress is half a sample or more of settling time (or the first feasible).
                if feasible and key[0] < best["key"][0] - 0.5 * ts:
                    best["improved_at"] = it
                if feasible and best["seconds_to_spec"] is None:
                    best["seconds_to_spec"] = time.perf_counter() - t0
                best["key"] = key

    stage, stage_start = 0, 0
    anchor = np.asarray(theta)
    it = 0
    for it in range(max_iterations):  # noqa: B007 (it is used after the loop)
        scale = jnp.asarray(SCALES[stage], dtype=theta.dtype)
        if it % check_every == 0:
            record(theta, it)
        lr = _cosine(learning_rate, it, max_iterations)
        theta, opt_state, values_now, aux = update(
            theta, opt_state, lr, fixed, mask, plants_arg, scale, lo_j, hi_j
        )

        values_np = np.asarray(values_now)
        j = int(np.argmin(values_np))
        info = aux[1] if is_robust else aux
        settle_s = np.asarray(info.settling_time)[j]
        over_s = np.asarray(info.overshoot)[j]
        entry = {
            "iteration": it,
            "seconds": time.perf_counter() - t0,
            "scale": float(scale),
            "loss": float(values_np[j]),
            "settling_time": float(np.max(settle_s)),
            "overshoot": float(np.max(over_s)),
            "best_settling_time": float(best["key"][0]),
        }
        history.append(entry)
        report(entry)

        # Continuation: shrink the widths once the gains stop moving at this width.
        done_in_stage = it + 1 - stage_start
        if done_in_stage % 10 == 0:
            moved = float(np.max(np.abs(np.asarray(theta) - anchor)))  # over 10 iterations
            if stage + 1 < len(SCALES) and (moved < 0.02 or done_in_stage >= stage_iterations):
                stage, stage_start = stage + 1, it + 1
            anchor = np.asarray(theta)
        # Early stop: finest width, feasible, and no better point for a while.
        if stage == len(SCALES) - 1 and it - stage_start >= patience:
            last = best["improved_at"] if best["improved_at"] is not None else stage_start
            if it - max(last, stage_start) >= patience:
                break
    record(theta, it + 1)  # the last iterate too
    report(None)
    iterations = it + 1
    seconds_to_spec = best["seconds_to_spec"]

    chosen, exact, checked = _verify(
        candidates, template, plant, experiment, spec, check_plants if is_robust else None
    )
    gains = dataclasses.replace(
        float_pid(template), kp=float(chosen[0]), kd=float(chosen[1]), ki=float(chosen[2])
    )
    smooth = _smooth_report(check, gains, plant, plants_arg, is_robust, theta, settings)

    worst = plant_set = None
    if is_robust:
        infos = checked
        worst = _worst(infos)
        plant_set = [
            {"params": v, "exact": _info_dict(i)} for v, i in zip(check_values, infos, strict=True)
        ]
        judged = worst
    else:
        judged = exact
    failing = failing_constraints(judged, spec)
    meets = not failing
    if meets and seconds_to_spec is None:
        seconds_to_spec = time.perf_counter() - t0
    if not meets:
        seconds_to_spec = None
    message = _message(meets, failing, judged, spec, is_robust, len(check_plants or []))
    return TuneResult(
        gains=gains,
        exact=exact,
        smooth=smooth,
        meets=meets,
        failing=failing,
        message=message,
        spec=spec,
        plant=plant,
        history=history,
        seconds=time.perf_counter() - t0,
        seconds_to_spec=seconds_to_spec,
        iterations=iterations,
        n_starts=int(theta.shape[0]),
        worst=worst,
        plant_set=plant_set,
    )


#: Compiled loss-and-gradient and check functions, by static configuration: a second tune()
#: with other starts, bounds or free gains (same batch size) compiles nothing.
_CACHE: dict = {}


def _compiled(template, spec, settings, robust, substeps, treedef):
    """(update, check, adam) for a static configuration, jitted once.

    update(theta, opt_state, lr, fixed, mask, plants, scale, lo, hi) -> (theta, opt_state,
        per-start losses, aux): one adam step (lr [log gain]) on the batch of starts,
        projected into the bounds [lo, hi] (log gains);
    check(theta, fixed, mask, plants, smoothing) -> (gains, StepInfo) per start.
    One compiled step, not a chain of small eager operations: measured, the eager adam update
    alone cost about 1 s of first-call compilation and a few ms per iteration.
    """
    key = (template, spec, settings, robust, substeps, treedef)
    if key not in _CACHE:
        experiment = step(spec.step, horizon=spec.horizon, sample_time=template.sample_time)
        loss = make_loss(template, experiment, spec, settings, robust=robust, substeps=substeps)
        value_and_grad = batched_value_and_grad(loss)
        adam = optax.scale_by_adam()
        checker = _checker(template, experiment, robust, substeps)

        def update(theta, opt_state, lr, fixed, mask, plants, scale, lo, hi):
            (_, (values, aux)), grad = value_and_grad(theta, fixed, mask, plants, scale)
            grad = jnp.where(jnp.isfinite(grad), grad, 0.0)  # a blown-up run teaches nothing
            direction, opt_state = adam.update(grad, opt_state, theta)
            theta = jnp.clip(theta - lr * direction, lo, hi) * mask[None]
            return theta, opt_state, values, aux

        def check(theta, fixed, mask, plants, smoothing):
            gains = gains_from_theta(theta, fixed[None], mask[None])
            return gains, checker(gains, plants, smoothing)

        _CACHE[key] = (jax.jit(update), jax.jit(check), adam)
    return _CACHE[key]


def _smooth_report(check, gains, plant, plants_arg, robust, theta, settings) -> StepInfo:
    """StepInfo of ``gains`` on ``plant``, smooth loop at the finest width of the continuation
    (through the compiled check: no new compilation unless the plant set differs)."""
    final = jax.tree.map(lambda w: jnp.zeros(()) + w, settings.smoothing.scaled(SCALES[-1]))
    fixed = jnp.asarray([gains.kp, gains.kd, gains.ki])
    mask = jnp.zeros(3, dtype=bool)  # every row: the fixed gains
    if robust:
        # One plant with the set's effects (friction included even where f_c = 0).
        values = {n: float(plant.get(n)) for n in ("M", "B_eq") if n in plant.param_names()}
        values["f_c"] = float(plant.get("f_c")) if plant.effect("coulomb") is not None else 0.0
        nominal = _stack([_with_params(plant, values)])
        if jax.tree.structure(nominal) != jax.tree.structure(plants_arg):
            nominal = _stack([plant])
        plants_arg = nominal
    else:
        plants_arg = plant
    _, info = check(jnp.zeros_like(theta), fixed, mask, plants_arg, final)
    return StepInfo(*(np.asarray(x)[0].item() for x in info))


def _cosine(lr0: float, k: int, n: int, alpha: float = 0.1) -> float:
    """Learning rate at iteration k of n: cosine decay from lr0 to alpha lr0 (optax's form)."""
    return lr0 * ((1 - alpha) * 0.5 * (1 + math.cos(math.pi * min(k, n) / n)) + alpha)


def _checker(template, experiment, robust, substeps):
    """metrics(gains (S, 3), plants, smoothing) -> StepInfo per start (for robust tuning, the
    field-wise worst over the plants); a run that blew up reports inf.

    ``smoothing`` is an argument: all-zero widths (traced, so not recognised as the exact forms
    at trace time) give exactly the hard clip and sign() anyway, since the smooth forms reduce to
    them at width 0; the same compiled function then serves the hard-clip tracking and the
    final report at the finest width.
    """

    def one(gains, plant, smoothing):
        info = step_metrics(
            plant,
            controller_with(template, gains),
            experiment,
            smoothing=smoothing,
            substeps=substeps,
        )
        bad = info.diverged
        return info._replace(
            settling_time=jnp.where(bad, jnp.inf, info.settling_time),
            overshoot=jnp.where(bad, jnp.inf, info.overshoot),
        )

    if robust:

        def worst(gains, plants, smoothing):
            infos = jax.vmap(one, in_axes=(None, 0, None))(gains, plants, smoothing)
            return StepInfo(
                *(
                    jnp.any(x) if name == "diverged" else jnp.max(x)
                    for name, x in zip(StepInfo._fields, infos, strict=True)
                )
            )

        return jax.vmap(worst, in_axes=(0, None, None))
    return jax.vmap(one, in_axes=(0, None, None))


def _verify(candidates, template, plant, experiment, spec, check_plants, tries: int = 4):
    """Best candidate that the exact simulator confirms; else the one closest to the spec.

    Returns (gains, exact StepInfo on ``plant``, per-plant exact StepInfos or None).
    """
    ranked = sorted(candidates.values(), key=lambda c: c[0])
    best = None
    for _key, g, _s, _o in ranked[:tries]:
        pid = controller_with(float_pid(template), [float(x) for x in g])
        if check_plants is None:
            info = exact_info(plant, pid, experiment)
            judged, per_plant = info, None
        else:
            per_plant = [exact_info(p, pid, experiment) for p in check_plants]
            judged = _worst(per_plant)
            info = exact_info(plant, pid, experiment)
        score = (
            0 if not failing_constraints(judged, spec) else 1,
            _violation(judged.settling_time, judged.overshoot, spec),
        )
        if best is None or score < best[0]:
            best = (score, g, info, per_plant)
        if score[0] == 0:
            break
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


def _limit(plant, pid) -> float:
    return float(voltage_limit(plant, pid))


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


def compare_tuners(
    plant: Plant | None = None,
    *,
    spec: Spec | None = None,
    start=None,
    free: Sequence[str] = GAIN_NAMES,
    controller: PID | None = None,
    seed: int = 0,
    bounds: Mapping | None = None,
    nm_max_evaluations: int = 600,
    progress: bool = False,
) -> dict:
    """Benchmark :func:`tune` against scipy's Nelder-Mead on the exact simulator (penalty
    objective, same start, log gains) and against the best point of a quasi-random (Sobol)
    grid over :data:`GRID_BOX` evaluated on the batched hard-clip simulator for the same wall
    time as :func:`tune` took (compilation included in both). All three search the same gain
    box: ``bounds`` (default :data:`DEFAULT_BOUNDS`), for the grid intersected with GRID_BOX.

    Returns a dict: one entry per method (settling_time [s], overshoot [%] on the exact
    simulator, seconds, seconds_to_spec, evaluations, gains) plus "ratios" and a printable
    "table".
    """
    from scipy.optimize import minimize
    from scipy.stats import qmc

    from jaxcart.batch import step_metrics_batch

    spec = spec or Spec()
    plant = handout_plant() if plant is None else plant
    free_mask = _free_mask(free)
    start_gains, template = _start_and_template(start, controller, free)
    experiment = step(spec.step, horizon=spec.horizon, sample_time=template.sample_time)
    say = (
        (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)
    )

    # 1. Gradient tuning (this module).
    say("compare: gradient tuner ...")
    ours = tune(
        plant,
        spec=spec,
        start=start,
        free=free,
        controller=controller,
        seed=seed,
        bounds=bounds,
        progress=progress,
    )
    budget = ours.seconds
    log_lo, log_hi = _bounds(bounds)

    # 2. Nelder-Mead on the exact simulator, penalty objective, same start.
    say("compare: Nelder-Mead on the exact simulator ...")
    base = np.where(
        free_mask & (start_gains <= 0), [ZERO_START[n] for n in GAIN_NAMES], start_gains
    )
    nm = {"evaluations": 0, "best": None, "first_feasible": None}
    t0 = time.perf_counter()

    def objective(x):
        g = np.where(free_mask, base, start_gains)
        # Projected into the tuner's box, so both search the same gains.
        g[free_mask] = np.exp(np.clip(x, log_lo[free_mask], log_hi[free_mask]))
        info = exact_info(plant, controller_with(template, list(g)), experiment)
        nm["evaluations"] += 1
        feasible = not failing_constraints(info, spec)
        if feasible and nm["first_feasible"] is None:
            nm["first_feasible"] = time.perf_counter() - t0
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
    # Initial simplex: +/- 30 % steps in each log gain (scipy's default 5 % is too timid here).
    simplex = np.vstack([x0] + [x0 + 0.3 * np.eye(x0.size)[i] for i in range(x0.size)])
    minimize(
        objective,
        x0,
        method="Nelder-Mead",
        options={
            "maxfev": nm_max_evaluations,
            "xatol": 1e-3,
            "fatol": 1e-4,
            "initial_simplex": simplex,
        },
    )
    nm_seconds = time.perf_counter() - t0
    _, nm_gains, nm_info = nm["best"]

    # 3. Quasi-random grid on the batched simulator for the same wall time.
    say(f"compare: grid of equal wall time ({budget:.1f} s) ...")
    friction = _has_friction(plant)
    smoothing = EXACT_FORMS if not friction else LossSettings().smoothing.scaled(SCALES[-1] / 4)
    lo = np.maximum(np.log([GRID_BOX[n][0] for n in GAIN_NAMES]), log_lo)
    hi = np.minimum(np.log([GRID_BOX[n][1] for n in GAIN_NAMES]), log_hi)
    sobol = qmc.Sobol(d=3, scramble=True, seed=seed)
    batch = 4096
    t0 = time.perf_counter()
    n_points, grid_best, grid_first = 0, None, None
    while time.perf_counter() - t0 < budget:
        g = np.exp(lo + sobol.random(batch) * (hi - lo))
        g = np.where(free_mask, g, start_gains)
        info = step_metrics_batch(plant, template, experiment, g, smoothing=smoothing)
        n_points += batch
        ok = (
            (~info.diverged)
            & (info.settling_time < spec.settling_time)
            & (info.overshoot < spec.overshoot)
        )
        if ok.any():
            if grid_first is None:
                grid_first = time.perf_counter() - t0
            i = int(np.argmin(np.where(ok, info.settling_time, np.inf)))
            if grid_best is None or info.settling_time[i] < grid_best[0]:
                grid_best = (float(info.settling_time[i]), g[i])
    grid_seconds = time.perf_counter() - t0
    if grid_best is not None:
        grid_gains = grid_best[1]
        grid_info = exact_info(plant, controller_with(template, list(grid_gains)), experiment)
    else:
        grid_gains, grid_info = None, None

    def entry(gains, info, seconds, to_spec, evaluations):
        return {
            "gains": None
            if gains is None
            else dict(zip(GAIN_NAMES, map(float, gains), strict=True)),
            "settling_time": None if info is None else _num(info.settling_time),
            "overshoot": None if info is None else _num(info.overshoot),
            "meets": info is not None and not failing_constraints(info, spec),
            "seconds": seconds,
            "seconds_to_spec": to_spec,
            "evaluations": evaluations,
        }

    result = {
        "gradient": entry(
            (ours.gains.kp, ours.gains.kd, ours.gains.ki),
            ours.exact,
            ours.seconds,
            ours.seconds_to_spec,
            ours.iterations * ours.n_starts,
        ),
        "nelder_mead": entry(
            nm_gains, nm_info, nm_seconds, nm["first_feasible"], nm["evaluations"]
        ),
        "grid": entry(grid_gains, grid_info, grid_seconds, grid_first, n_points),
    }

    def ratio(a, b):
        try:
            a, b = float(a), float(b)
        except (TypeError, ValueError):
            return None
        return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else None

    g = result["gradient"]
    result["ratios"] = {
        "settling_nelder_mead_over_gradient": ratio(
            result["nelder_mead"]["settling_time"], g["settling_time"]
        ),
        "settling_grid_over_gradient": ratio(result["grid"]["settling_time"], g["settling_time"]),
        "seconds_nelder_mead_over_gradient": ratio(nm_seconds, ours.seconds),
        "seconds_to_spec_nelder_mead_over_gradient": ratio(
            nm["first_feasible"], ours.seconds_to_spec
        ),
    }
    result["table"] = _compare_table(result)
    return result


def _compare_table(result) -> str:
    def f(x, digits=3):
        return "-" if x is None else (x if isinstance(x, str) else f"{x:.{digits}f}")

    lines = [
        f"{'method':<34s}{'settling [s]':>13s}{'overshoot [%]':>15s}{'meets':>7s}"
        f"{'wall [s]':>10s}{'to spec [s]':>13s}{'evaluations':>13s}"
    ]
    names = {
        "gradient": "gradient (this tuner, exact check)",
        "nelder_mead": "scipy Nelder-Mead, exact simulator",
        "grid": "Sobol grid, equal wall time",
    }
    for key, label in names.items():
        e = result[key]
        lines.append(
            f"{label:<34s}{f(e['settling_time']):>13s}{f(e['overshoot'], 2):>15s}"
            f"{'yes' if e['meets'] else 'no':>7s}{f(e['seconds'], 1):>10s}"
            f"{f(e['seconds_to_spec'], 2):>13s}{e['evaluations']:>13,d}"
        )
    r = result["ratios"]
    lines.append(
        "ratios: settling NM/gradient {}, grid/gradient {}; wall time NM/gradient {}; "
        "time to spec NM/gradient {}".format(
            f(r["settling_nelder_mead_over_gradient"]),
            f(r["settling_grid_over_gradient"]),
            f(r["seconds_nelder_mead_over_gradient"], 2),
            f(r["seconds_to_spec_nelder_mead_over_gradient"], 2),
        )
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
    "penalty_objective",
    "HANDOUT_START",
    "DEFAULT_BOUNDS",
    "DEFAULT_ROBUST",
    "GRID_BOX",
]
