"""The tuning problem as :func:`tuning.design.tune.tune` is asked it, checked and placed: the
start, the free parameters, the search box (in logs), the plant or the robust plant set, and
the batch of starts.

Every check that can fail is here, before anything compiles: a :class:`UserError` names what
is wrong and how to say it right.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from hw.control_law import PID, float_pid
from jaxcart.errors import UserError
from jaxcart.experiments import Experiment, step
from jaxcart.parallel import batch_sharding, devices, put, replicated
from jaxcart.params import Plant
from jaxcart.plantspec import build_plant, handout_plant
from tuning.design.limits import gain_limits
from tuning.design.losses import GAIN_NAMES, PARAM_NAMES, LossSettings, Spec, params_of

#: The handout's suggested starting gains (kp [V/m], kd [V s/m], ki [V/(m s)]).
HANDOUT_START = (40.0, 5.0, 5.0)
#: The box of the parameters before the cart is known: kp [V/m], kd [V s/m], ki [V/(m s)], the
#: derivative filter tau [s] (0.1 ms to 0.1 s), the back-calculation gain kb [1/s] and the
#: software limit v_limit [V] (at most the lab's 6 V amplifier range). The upper ends of kp
#: and kd are then derived from the cart (:func:`search_box`, :mod:`tuning.design.limits`:
#: the drive's voltage inside the settling band, the encoder's ripple), unless ``bounds=`` /
#: ``--bound`` give them.
DEFAULT_BOUNDS = {
    "kp": (1e-2, 1e4),
    "kd": (1e-3, 1e3),
    "ki": (1e-3, 200.0),
    "tau": (1e-4, 0.1),
    "kb": (1e-2, 1e3),
    "v_limit": (0.5, 6.0),
}
#: Where a free parameter starts when its start value is 0 (log space needs a positive value).
ZERO_START = {"kp": 1.0, "kd": 0.1, "ki": 0.1, "tau": 1e-3, "kb": 1.0, "v_limit": 6.0}
#: Robust tuning's default plant set: intervals of parameters (M as a fraction of nominal).
DEFAULT_ROBUST = {"B_eq": (3.0, 7.0), "f_c": (0.0, 1.0), "M": (0.9, 1.1)}


@dataclass
class TuningProblem:
    """What :func:`tuning.design.tune.tune` was asked, checked and placed: the specification,
    the controller template, the free parameters (names and mask over :data:`PARAM_NAMES`),
    the start, the box (logs ``lo``, ``hi``; ``box`` in units), the plant (or stacked set
    ``plants_arg``), the plants the result is checked on (robust tuning; else None) and the
    limits of the gains derived from the cart (:func:`tuning.design.limits.gain_limits`: those
    the box took, the user's bounds winning)."""

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
    experiment: Experiment
    plants_arg: Plant
    substeps: int | None
    check_plants: list | None
    check_values: list | None
    limits: dict

    @property
    def robust(self) -> bool:
        return self.check_plants is not None


def tuning_problem(
    plant, *, spec, start, free, controller, robust, bounds, settings, substeps, n_check, seed
) -> TuningProblem:
    """The checked problem of :func:`tuning.design.tune.tune` (a UserError names what is
    wrong)."""
    plant = handout_plant() if plant is None else plant
    mask = free_mask(free)
    free = tuple(n for n in PARAM_NAMES if n in free)
    start_params, template = start_and_template(start, controller, free)
    template = float_pid(template)
    if "kb" in free and template.anti_windup != "back_calculation":
        raise UserError(
            "free kb: the back-calculation gain acts only with anti_windup='back_calculation' "
            "(--anti-windup back_calculation)"
        )
    lo, hi, box, limits = search_box(plant, template, spec, free, bounds)
    experiment = step(spec.step, horizon=spec.horizon, sample_time=template.sample_time)
    plants_arg, check_plants, check_values = plant_set(plant, robust, n_check, seed)
    return TuningProblem(
        spec=spec,
        settings=settings,
        plant=plant,
        template=template,
        free=free,
        free_mask=mask,
        start_params=start_params,
        lo=lo,
        hi=hi,
        box=box,
        experiment=experiment,
        plants_arg=plants_arg,
        substeps=substeps,
        check_plants=check_plants,
        check_values=check_values,
        limits=limits,
    )


def start_and_template(start, controller, free):
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


def free_mask(free) -> np.ndarray:
    """Which of :data:`PARAM_NAMES` are free (a UserError for an unknown name or none)."""
    free = tuple(free)
    unknown = [n for n in free if n not in PARAM_NAMES]
    if unknown or not free:
        raise UserError(
            f"free gains {', '.join(free) or '(none)'}: name one or more of "
            f"{', '.join(PARAM_NAMES)}"
        )
    return np.array([n in free for n in PARAM_NAMES])


def search_box(plant, template, spec: Spec, free, bounds):
    """(log lower, log upper, the box {name: (lo, hi)}, the limits it took): the box of
    :func:`log_bounds` with the upper ends of kp and kd derived from ``plant`` for the
    controller ``template`` and the spec's step (:func:`tuning.design.limits.gain_limits`),
    where ``bounds`` does not give them."""
    tau_low = DEFAULT_BOUNDS["tau"][0] if "tau" in free else None
    limits = gain_limits(plant, template, spec.step, tau_low=tau_low)
    limits = {n: lim for n, lim in limits.items() if n not in (bounds or {})}
    return (*log_bounds(bounds, limits), limits)


def log_bounds(bounds, limits=None):
    """(log lower, log upper) bounds in :data:`PARAM_NAMES` order, and the merged dict:
    :data:`DEFAULT_BOUNDS`, the upper ends of ``limits`` ({name:
    :class:`tuning.design.limits.Limit`}, derived from the cart), then ``bounds``."""
    merged = dict(DEFAULT_BOUNDS)
    for name, limit in (limits or {}).items():
        lo = merged[name][0]
        merged[name] = (lo, max(float(limit.bound), 10.0 * lo))
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


def stack_plants(plants: Sequence[Plant]) -> Plant:
    """One plant whose every leaf stacks the leaves of ``plants`` (same effects) on axis 0."""
    return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x, dtype=float) for x in xs]), *plants)


def has_force_effects(plant: Plant) -> bool:
    """True where force effects act (the loop then needs sub-steps and narrow widths)."""
    return bool(plant.stage("force"))


def plant_set(plant: Plant, robust, n_check: int, seed: int):
    """(plants_arg: the plant on the device or the stacked training set, check_plants,
    check_values: the set the result is checked on and its parameters, None without robust
    tuning)."""
    if robust is False or robust is None:
        # On the device once (a Python number is transferred again at every call).
        return jax.tree.map(put, plant), None, None
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
    return stack_plants(train), check_plants, check_values


def base_start(mask: np.ndarray, start_params: np.ndarray) -> np.ndarray:
    """The start parameters with every free one (``mask``) that starts at 0 moved to
    :data:`ZERO_START` (log space needs a positive value)."""
    return np.where(mask & (start_params <= 0), [ZERO_START[n] for n in PARAM_NAMES], start_params)


def model_start(p: TuningProblem) -> np.ndarray | None:
    """A pole-placement design for the plant being tuned, as a start (:data:`PARAM_NAMES`
    order), or None where it would not differ from the given start (or kp and kd are fixed).

    The PD part is placed by the textbook's second-order design on the cart's linear model
    m y'' + c y' = gamma v (c = B_eq + B_emf; the nominal plant's, friction, delay and
    saturation left out): the closed loop m s^2 + (c + gamma kd) s + gamma kp has the damping
    ratio zeta of the spec's overshoot, zeta = -ln(OS) / sqrt(pi^2 + ln^2 OS), and settles
    into the spec's band at its settling bound, omega_n = -ln(band sqrt(1 - zeta^2)) /
    (zeta T_max). So kp = m omega_n^2 / gamma and kd = (2 zeta omega_n m - c) / gamma; where the
    cart's own damping is already more than that (kd <= 0), kd starts where a zero start would
    (:data:`ZERO_START`). Only free kp and kd take these values; every other parameter keeps the
    given start's. Inside the box like every start."""
    if not p.free_mask[:2].any():
        return None
    try:
        plant = p.plant
        m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    except (AttributeError, TypeError, ValueError):
        return None
    spec = p.spec
    shoot = min(max(float(spec.overshoot) / 100.0, 1e-4), 0.9)
    zeta = -math.log(shoot) / math.sqrt(math.pi**2 + math.log(shoot) ** 2)
    band = min(max(float(spec.band), 1e-6), 0.5)
    omega = -math.log(band * math.sqrt(1.0 - zeta**2)) / (zeta * float(spec.settling_time))
    if not all(math.isfinite(x) and x > 0 for x in (m, gamma, omega)) or not math.isfinite(c):
        return None
    kp = m * omega**2 / gamma
    kd = (2.0 * zeta * omega * m - c) / gamma
    given = base_start(p.free_mask, p.start_params)
    designed = given.copy()
    for i, value in ((0, kp), (1, kd if kd > 0 else ZERO_START["kd"])):
        if p.free_mask[i]:
            designed[i] = min(max(value, math.exp(p.lo[i])), math.exp(p.hi[i]))
    if np.allclose(designed[p.free_mask], given[p.free_mask], rtol=1e-3):
        return None
    return designed


def starts(p: TuningProblem, n_starts: int, spread: float, seed: int):
    """(theta, rows): the logs of the starts, on the devices, and their placement. The given
    start, then (with two or more starts) a pole-placement design for the plant
    (:func:`model_start`), then log-normal perturbations of the given start's free parameters
    (``spread``: standard deviation of their logs), clipped into the box."""
    theta0 = np.log(np.where(p.free_mask, base_start(p.free_mask, p.start_params), 1.0))
    rng = np.random.default_rng(seed)
    noise = spread * rng.standard_normal((n_starts - 1, len(PARAM_NAMES)))
    blocks = [theta0[None], theta0[None] + noise]
    designed = model_start(p) if n_starts > 1 else None
    if designed is not None:
        model = np.log(np.where(p.free_mask, designed, 1.0))
        blocks = [theta0[None], model[None], (theta0[None] + noise)[: n_starts - 2]]
    theta = np.concatenate(blocks) * p.free_mask
    theta = np.clip(theta, p.lo, p.hi) * p.free_mask
    # The batch of starts is sharded over every device: pad it to a multiple with copies of the
    # first start (never new random ones), so the result does not depend on the device count.
    n_dev = len(devices())
    theta = np.concatenate([theta, np.repeat(theta[:1], -n_starts % n_dev, axis=0)])
    # One device: the placement the compiled update returns (a second signature otherwise).
    rows = batch_sharding() if n_dev > 1 else replicated()
    return put(theta, float, rows), rows
