"""Fit plant parameters to recordings: gradient through the smoothed simulator, a
Levenberg-Marquardt polish, a last Gauss-Newton polish on the exact simulator, standard errors
that survive autocorrelated residuals, and identifiability.

    recordings --prepare--> segments (a tap: its coasting part, found automatically;
                               |      encoder counts: the middle of each count)
    theta = [log B_eq, log f_c, ... (shared) | y0, yd0 of each recording (nuisance)]
                               v
    residuals r(theta) = y_model(theta) - y_measured      (every segment, metres)
      smoothing width wide -> narrow:  Levenberg-Marquardt, each iteration trying four
      damping values in one batched, sharded run (J = jax.jacfwd of r through
      jaxcart.simulate, float64; adam first at the widest, ``adam_steps``)
      -> Gauss-Newton on jaxcart.exact.simulate_exact (residuals and Jacobian exact)
      -> robust covariance -> "not identifiable" where the relative standard error exceeds
         max_rel_stderr (held at its start value, the rest refitted) -> RMS before and after
      -> the residual against the noise floor: a model that does not explain the data is
         flagged and its standard errors widened to what the residual supports

Nuisance values: a tap's position and velocity where its coasting starts (free); a closed or
open loop's start position, bounded to the encoder count it starts in (the encoder reads 0
there). Positive parameters are fitted as logarithms.

Standard errors. Residuals are autocorrelated: the encoder's error stays put while the cart is
slow or at rest (one count's error for hundreds of samples), model error is smooth in time. The
naive sigma^2 (J^T J)^-1 counts those samples as independent and is far too small (on a
P-controlled step 10-20 times). The reported error is the sandwich (J^T J)^-1 S (J^T J)^-1
(:func:`tuning.estimation.engine.covariance.covariances`): samples are grouped into runs within
one count, whose CR3-adjusted scores enter a Newey-West long-run covariance, and the encoder's
known share (q^2/12 per run) is a floor. Checked over many seeds (tests/test_fit.py): about
68 % of the truths within one standard error and 95 % within two, slightly conservative on
encoder-only data. The naive value is kept beside it (``stderr_naive``). Where the RMS error
exceeds MISFIT_RATIO times the noise floor (q / sqrt(12) and white noise) the residual is model
error, not noise: the fit says the model does not explain the data, and each standard error is
at least the naive one times sqrt(N / n_eff), n_eff the independent samples the residual's
autocorrelation leaves (tests/test_fit_honesty.py). A parameter held, and an optimizer stopped
at its iteration cap, are reported (``FitResult.warnings``: the printout, the JSON and the
plant file's [fit] table).

>>> import jaxcart as jc
>>> from jaxcart.synthetic import make_recording
>>> truth = jc.tap_plant(B_eq=3.0, effects=(jc.Coulomb(f_c=0.5),))
>>> rec = make_recording(truth, None, jc.tap(1.0, horizon=0.6), seed=0)
>>> result = fit([rec], ("B_eq", "f_c"), progress=False)
>>> round(result.params["B_eq"].value, 2), round(result.params["f_c"].value, 2)
(3.0, 0.5)
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time as _time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart import plantspec
from jaxcart.errors import UserError
from jaxcart.experiments import Experiment
from jaxcart.parallel import put, sharded_map
from jaxcart.params import Plant
from jaxcart.plantspec import handout_plant
from jaxcart.smooth_sim import simulate_smooth
from jaxcart.smoothing import Smoothing, continuation
from jaxcart.workers import SERIAL
from tuning.estimation.engine import parameters as P
from tuning.estimation.engine.covariance import Covariance, covariance
from tuning.estimation.engine.exact_polish import STAIRCASE, gauss_newton
from tuning.estimation.engine.lm import (
    LM_DAMPING,
    LM_TOLERANCE,
    LM_TOLERANCE_WIDE,
    MAX_STEP,
    adam,
    levenberg_marquardt,
)
from tuning.estimation.engine.noise import (
    effective_samples,
    encoder_count,
    floor_of,
    misfits,
    noise_level,
)
from tuning.estimation.engine.parameters import base_name
from tuning.estimation.engine.segments import Segment
from tuning.estimation.engine.segments import prepare as prepare_segment

#: Other names for parameters: the issue's "v_limit" is the amplifier's saturation v_sat.
ALIASES = {"v_limit": "v_sat"}


def not_fitted() -> dict:
    """{parameter: why} of the parameters a fit does not offer: a sensor's, read from the data."""
    return {
        p.name: f"the sensor's {p.doc} is read from each recording (every position is a whole "
        "number of them); it is not fitted"
        for cls in plantspec.REGISTRY.values()
        for p in cls.params
        if p.role == "sensor"
    }


def fittable() -> tuple:
    """Parameters a fit offers: the plant's corrections and every registered effect's (naming
    one adds its effect; a vector such as f_track is fitted element by element, as f_track[0],
    f_track[1], ...), from the registry as it is now."""
    skip = not_fitted()
    effects = [p.name for c in plantspec.REGISTRY.values() for p in c.params if p.name not in skip]
    return P.CORRECTABLE + tuple(effects)


def default_start() -> dict:
    """Starting values [SI] for parameters a plant does not have yet: each one's declared start
    (a vector's, element by element)."""
    out = {}
    for n in fittable():
        if n in ("B_eq", "M"):
            continue
        decl = plantspec.param(n)
        out[n] = (decl.start,) * decl.size if decl.size else decl.start
    return out


def unit_of(name: str) -> str:
    """The SI unit of a fitted name (``v_sat@2``, ``f_track[1]``, the alias ``v_limit``)."""
    try:
        return plantspec.unit(canonical(base_name(name)))
    except KeyError:
        return ""


#: Nuisance values and their internal units (the optimizer's unit step): y0, the initial
#: position [m]; yd0, the initial velocity [m/s].
NUISANCE_SCALE = {"y0": 1e-3, "yd0": 0.1}


class Nuisance(NamedTuple):
    """A per-recording value fitted beside the plant: value = base + scale * theta, or, when
    ``bounded``, base + scale * sigmoid(theta) (within [base, base + scale]). name: "y0" [m] or
    "yd0" [m/s]."""

    name: str
    base: float
    scale: float
    bounded: bool = False

    def value(self, theta, xp=np):
        if self.bounded:
            return self.base + self.scale / (1 + xp.exp(-theta))
        return self.base + self.scale * theta

    def slope(self, theta) -> float:
        """d value / d theta."""
        if self.bounded:
            e = math.exp(-abs(float(theta)))
            return self.scale * e / (1 + e) ** 2
        return self.scale


#: Points per batched evaluation (every call is padded to a multiple: one compiled program):
#: the damping values one Levenberg-Marquardt iteration tries at once.
LM_BATCH = len(LM_DAMPING)
#: Bounded nuisance values stay within sigmoid(+-BOUNDED_LIMIT) of their range.
BOUNDED_LIMIT = 6.0
#: Segments are padded to a multiple of this many samples (fewer recompilations).
PAD = 256


@dataclass(frozen=True)
class FitSettings:
    """How the fit runs.

    widths: velocity smoothing of friction's sign(), wide -> narrow (continuation) [m/s]
    voltage_width: smoothing of the clip corners [V]
    adam_steps: adam iterations at the widest width (0: Levenberg-Marquardt only; adam leads
        ill-conditioned fits, e.g. friction along the track, to a better minimum)
    learning_rate: adam step in internal units (log of a parameter, or mm and 0.1 m/s)
    lm_iterations: at most this many Levenberg-Marquardt iterations at each width
    exact_iterations: at most this many Gauss-Newton iterations on the exact simulator
    substeps: sub-steps per sample of the smooth simulator (None: the one policy,
        :func:`jaxcart.substeps.substeps_per_sample`)
    max_rel_stderr: a parameter whose standard error exceeds this fraction of its value is
        reported as not identifiable (and held at its starting value)
    tap_margin: skip this long after the peak speed of a tap, where the hand may still push [s]
    quantization: the encoder count [m]; None: found in each recording (:func:`encoder_count`)
    """

    widths: tuple[float, ...] = tuple(1e-2 * f for f in continuation(1e-2, 3))
    voltage_width: float = 1e-3
    adam_steps: int = 40
    learning_rate: float = 0.02
    lm_iterations: int = 30
    exact_iterations: int = 10
    substeps: int | None = None
    max_rel_stderr: float = 0.5
    tap_margin: float = 0.02
    quantization: float | None = None


@dataclass(frozen=True)
class Estimate:
    """One fitted value: value [SI] and its standard error (HAC, see the module docstring);
    both None when the parameter is not identifiable from the data (``note`` says why)."""

    name: str
    value: float | None
    stderr: float | None
    identifiable: bool = True
    stderr_naive: float | None = None
    note: str = ""
    held_at: float | None = None  # the value a parameter not identified is held at [SI]
    #: ("upper" | "lower", bound [SI]) where the value sits on an edge of the range the fit
    #: holds it in (engine.parameters.at_edge): then it is no estimate
    edge: tuple | None = None

    @property
    def edge_note(self) -> str:
        """One line saying the value is on an edge of its range ("" when it is not)."""
        if self.edge is None:
            return ""
        side, _ = self.edge
        lo, hi = P.bounds(canonical(base_name(self.name)))
        unit = unit_of(self.name)
        return (
            f"{self.name} = {self.value:.4g} {unit} is at the {side} edge of its allowed range "
            f"[{lo:.4g}, {hi:.4g}] {unit}: the data push it beyond what the fit allows, so it "
            "is no estimate (a step recorded late, data in other units, or an effect left "
            "out: jaxcart diagnose)"
        )

    def to_json(self) -> dict:
        out = {"value": _finite(self.value), "stderr": _finite(self.stderr)}
        if self.edge is not None:
            out["at_edge"] = {"side": self.edge[0], "bound": self.edge[1]}
        if not self.identifiable:
            out["identifiable"] = False
            out["note"] = self.note
            if self.held_at is not None:
                out["held_at"] = _finite(self.held_at)
        else:
            out["stderr_naive"] = _finite(self.stderr_naive)
        return out


@dataclass(frozen=True, eq=False)
class SegmentFit:
    """The fit seen on one segment: the measured positions and the model's before and after
    (smooth at the narrowest width, and exact) [m], their RMS errors [m], fitted nuisance."""

    name: str
    kind: str
    time: np.ndarray
    measured: np.ndarray
    before: np.ndarray
    after: np.ndarray
    before_exact: np.ndarray | None
    after_exact: np.ndarray | None
    nuisance: dict
    plant: Plant

    @property
    def rms_before(self) -> float:
        return _rms(self.before - self.measured)

    @property
    def rms_after(self) -> float:
        return _rms(self.after - self.measured)

    @property
    def rms_before_exact(self) -> float | None:
        return None if self.before_exact is None else _rms(self.before_exact - self.measured)

    @property
    def rms_after_exact(self) -> float | None:
        return None if self.after_exact is None else _rms(self.after_exact - self.measured)


@dataclass(frozen=True, eq=False)
class FitResult:
    """The outcome of :func:`fit`.

    params: {name as asked: :class:`Estimate`}; values: every plant value the fit used, by
    canonical name (fitted, or held) [SI]; segments: a :class:`SegmentFit` per recording;
    correlation: {(a, b): correlation} of the identified parameters; n_data: samples fitted;
    seconds: wall time [s]; smoothing: the narrowest smoothing used (None for a diagnosis's
    fit, whose values are the exact simulator's); history: (width [m/s],
    Levenberg-Marquardt iterations, RMS [m]) per width (at the narrowest, of the run kept:
    the continuation's or the direct start's); exact_polish: True when the last polish
    ran on the exact simulator; stages: each optimizer run ({"stage", "iterations", "cap",
    "converged"}, and "superseded": True for the continuation's runs where the direct start
    at the narrowest width was kept instead: they do not count for ``converged``);
    noise_floor: the RMS error [m] a correct model would leave (encoder count q/sqrt(12) and
    white noise); n_effective: independent samples the final residual is worth
    (:func:`effective_samples`); misfit: why the model does not explain the data ("" when it
    does: RMS within :data:`MISFIT_RATIO` of the noise floor), in which case the standard errors
    are widened to what the residual supports.
    """

    params: dict
    values: dict
    segments: list
    correlation: dict
    n_data: int
    seconds: float
    smoothing: Smoothing | None
    history: list = field(default_factory=list)
    exact_polish: bool = False
    stages: list = field(default_factory=list)
    noise_floor: float = 0.0
    n_effective: float = 0.0
    misfit: str = ""
    #: The fitted plant itself, effects included, where the fit made one (a diagnosis's chosen
    #: structure, :func:`tuning.estimation.diagnose.as_fit.fit_result`); None: from ``values``.
    cart: Plant | None = None

    @property
    def converged(self) -> bool:
        """False when an optimizer stopped at its iteration cap (the fit may be unfinished)."""
        return all(
            s["converged"]
            for s in self.stages
            if not s.get("superseded") and not s.get("intermediate")
        )

    @property
    def warnings(self) -> list[str]:
        """One line for each thing the numbers do not show: a model that does not explain the
        data, a parameter held at its start value, an optimizer stopped at its cap."""
        out = [self.misfit] if self.misfit else []
        out += [e.edge_note for e in self.params.values() if e.edge is not None]
        held = {n: e for n, e in self.params.items() if not e.identifiable}
        for n, e in held.items():
            out.append(f"{n}: {e.note}; the other errors are conditional on that value")
        for s in self.stages:
            if not s["converged"] and not s.get("superseded") and not s.get("intermediate"):
                out.append(
                    f"{s['stage']} stopped at its iteration cap ({s['cap']}) before converging; "
                    "the values may not be the best fit"
                )
        return out

    def _total(self, attr) -> float | None:
        parts = [(getattr(s, attr), s.measured.size) for s in self.segments]
        if any(v is None for v, _ in parts):
            return None
        return math.sqrt(sum(v * v * n for v, n in parts) / sum(n for _, n in parts))

    @property
    def rms_before(self) -> float:
        """RMS position error [m] of the smooth model with the starting values."""
        return self._total("rms_before")

    @property
    def rms_after(self) -> float:
        """RMS position error [m] of the smooth model with the fitted values."""
        return self._total("rms_after")

    @property
    def rms_before_exact(self) -> float | None:
        return self._total("rms_before_exact")

    @property
    def rms_after_exact(self) -> float | None:
        """RMS position error [m] of the exact simulator with the fitted values."""
        return self._total("rms_after_exact")

    def per_recording_json(self) -> dict:
        """{recording name: {parameter: {"value", "stderr"}, "rms_before", "rms_after"}} of the
        parameters fitted per recording (``name@k``), with each recording's exact RMS [m]."""
        out = {}
        for k, seg in enumerate(self.segments):
            own = {
                n.split("@")[0]: e.to_json() for n, e in self.params.items() if n.endswith(f"@{k}")
            }
            if own:
                names = [s.name for s in self.segments]
                key = seg.name if names.count(seg.name) == 1 else f"{seg.name} #{k + 1}"
                out[key] = {
                    "parameters": own,
                    "rms_before": seg.rms_before_exact,
                    "rms_after": seg.rms_after_exact,
                }
        return out

    def plant(self, base: Plant | None = None) -> Plant:
        """The fitted plant for closed-loop use: ``base`` (default: :attr:`cart` where the fit
        made one, else the first closed- or open-loop recording's plant, else the handout's)
        with the fitted values."""
        if base is None and self.cart is not None:
            return self.cart
        if base is None:
            driven = [s.plant for s in self.segments if s.plant.motor_connected]
            base = driven[0] if driven else handout_plant()
        return with_values(base, assemble(base, self.values))

    def to_json(self) -> dict:
        """{"params": {name: {"value", "stderr"}}, "rms_before", "rms_after" [m], ...}: the
        RMS values are the exact simulator's where it ran, else the smooth model's."""
        exact = self.rms_after_exact is not None
        return {
            "params": {n: e.to_json() for n, e in self.params.items()},
            "rms_before": self.rms_before_exact if exact else self.rms_before,
            "rms_after": self.rms_after_exact if exact else self.rms_after,
            "rms_before_smooth": self.rms_before,
            "rms_after_smooth": self.rms_after,
            "n_data": self.n_data,
            "recordings": [
                {
                    "name": s.name,
                    "kind": s.kind,
                    "start_time": float(s.time[0]),
                    "stop_time": float(s.time[-1]),
                    "rms_before": s.rms_before_exact,
                    "rms_after": s.rms_after_exact,
                    "rms_before_smooth": s.rms_before,
                    "rms_after_smooth": s.rms_after,
                    "nuisance": {k: e.to_json() for k, e in s.nuisance.items()},
                }
                for s in self.segments
            ],
            "correlation": {f"{a},{b}": c for (a, b), c in self.correlation.items()},
            "values": dict(self.values),
            "seconds": self.seconds,
            "model_explains_data": not self.misfit,
            "noise_floor": self.noise_floor,
            "n_effective": self.n_effective,
            "optimizer": list(self.stages),
            "converged": self.converged,
            "held": {n: e.held_at for n, e in self.params.items() if not e.identifiable},
            "per_recording": self.per_recording_json(),
            "warnings": self.warnings,
        }


# ---------------------------------------------------------------- names and plants


def canonical(name: str) -> str:
    """The plant's name for a parameter (``v_limit`` -> ``v_sat``)."""
    return ALIASES.get(name, name)


def parse_params(text) -> tuple[str, ...]:
    """Parameter names from "B_eq,f_c" (or a sequence of names), checked against the known."""
    names = [n.strip() for n in text.split(",")] if isinstance(text, str) else list(text)
    names = [n for n in names if n]
    known = _known_names()
    expanded = []
    for n in names:
        skip = not_fitted()
        if canonical(n) in skip:
            raise UserError(f"--params: {n}: {skip[canonical(n)]}")
        if base_name(n) in known and "[" in n:
            expanded.append(n)  # one element of a vector, as returned by the fit
            continue
        size = plantspec.param(canonical(n)).size if canonical(n) in known else 0
        if size:
            expanded += [f"{n}[{i}]" for i in range(size)]
            continue
        expanded.append(n)
        if canonical(n) not in known:
            raise UserError(
                f"--params: unknown parameter {n!r}; fit any of "
                f"{', '.join(fittable())} (v_limit = v_sat), or another plant "
                f"parameter: {', '.join(sorted(known))}"
            )
    if len({canonical(n) for n in expanded}) != len(expanded):
        raise UserError(f"--params {','.join(names)}: a parameter is named twice")
    return tuple(expanded)


def _element(name: str) -> int | None:
    return int(name[name.index("[") + 1 : -1]) if "[" in name else None


def assemble(plant: Plant, values: dict, xp=np) -> dict:
    """{name: value} with vector elements ("f_track[2]") gathered into their vectors (the
    plant's current vector where an element is not given); scalars pass through."""
    out, vectors = {}, {}
    for name, value in values.items():
        i = _element(name)
        if i is None:
            out[name] = value
            continue
        base = base_name(name)
        if base not in vectors:
            have = plant.get(base) if base in plant.param_names() else default_start()[base]
            vectors[base] = list(have) if isinstance(have, tuple) else list(xp.asarray(have))
        vectors[base][i] = value
    for base, items in vectors.items():
        out[base] = (
            xp.stack([xp.asarray(v) for v in items])
            if xp is not np
            else tuple(float(v) for v in items)
        )
    return out


def _known_names() -> set:
    return set(fittable()) | set(plantspec.parameter_names())


def _drives_nothing(name: str, plant: Plant) -> bool:
    """True for an effect's parameter of the drive (amplifier, motor) on an unplugged motor."""
    return (
        not plant.motor_connected
        and plantspec.effect_of_param(base_name(name)) is not None
        and P.is_drive(name)
    )


def with_values(plant: Plant, values: dict) -> Plant:
    """``plant`` with named values [SI] through the plant spec (a name of an effect the plant
    lacks adds it). Names the plant cannot have (a drive effect on a tap) are ignored."""
    values = {canonical(k): v for k, v in values.items()}
    values = {k: v for k, v in values.items() if not _drives_nothing(k, plant)}
    return plantspec.build_plant(values, base=plant, check=False)


_log_scaled = P.is_log
LINEAR_SCALE = P.LINEAR_SCALE


def to_value(name: str, theta, xp=np):
    """A parameter's value [SI] from its internal coordinate (:mod:`.engine.parameters`)."""
    return xp.exp(theta) if P.is_log(name) else LINEAR_SCALE * theta


def to_theta(name: str, value: float) -> float:
    """The internal coordinate of a parameter value (inverse of :func:`to_value`)."""
    return P.to_theta(name, value)


def plant_values(plant: Plant, names=None) -> dict:
    """{name: float} of those ``names`` (default: every fittable one) the plant has."""
    names = fittable() if names is None else names
    have = set(plant.param_names())
    return {n: float(plant.get(n)) for n in names if n in have}


# ---------------------------------------------------------------- segments


def _default_start(name: str) -> float:
    start = default_start().get(base_name(name), 1.0)
    return float(start[_element(name)] if isinstance(start, tuple) else start)


def _initial_value(name, value):
    """A starting value [SI]: a float, or a tuple of floats for a vector parameter."""
    try:
        if isinstance(value, list | tuple | np.ndarray):
            return tuple(float(v) for v in value)
        return float(value)
    except (TypeError, ValueError):
        raise UserError(f"initial value {name} = {value!r}: give a number (SI units)") from None


def prepare(recording, params, values: dict, settings: FitSettings) -> Segment:
    """A recording as the engine's :class:`Segment` (:func:`~.engine.segments.prepare`: the
    coasting part of a tap, or the whole run of a closed or open loop) with what this fit adds:
    the plant with the start ``values`` (and each fitted effect it lacks at a start where it acts
    on these data), the fitted ``params`` that act on it, and its nuisance values: a tap's y0,
    yd0 (free); a run's y0 (bounded: the encoder reads 0 at the start, the cart is somewhere
    within that count)."""
    seg = prepare_segment(recording, quantization=settings.quantization, margin=settings.tap_margin)
    gains = seg.controller
    if seg.kind == "closed_loop" and gains.ki == 0 and gains.kp == 0 and gains.kd == 0:
        raise UserError(f"{seg.name}: [controller] has all gains 0; give the gains that ran")
    raw = np.asarray(recording.position, dtype=float)
    plant = with_values(recording.plant(), values)
    canon = [canonical(p) for p in params]
    peaks = _peaks(recording, plant)
    starts = default_start()
    for p in canon:  # a fitted effect the plant lacks starts where it acts on these data
        b = base_name(p)
        if b in starts and b not in plant.param_names() and not _drives_nothing(b, plant):
            start = starts[b] if plantspec.param(b).size else P.start_for(b, peaks, raw.mean())
            plant = with_values(plant, {b: start})
    acting = tuple(p for p in canon if base_name(p) in plant.param_names())
    if seg.kind == "tap":
        nuisance = (
            Nuisance("y0", 0.0, NUISANCE_SCALE["y0"]),
            Nuisance("yd0", 0.0, NUISANCE_SCALE["yd0"]),
        )
    else:
        # y0 lies within the first count, widened by 4 noise levels either side where the data
        # are not whole counts (a bounded nuisance).
        sigma = 0.0 if encoder_count(raw) > 0 else noise_level(raw)
        width = seg.quantization + 8 * sigma
        y0 = seg.experiment.y0
        nuisance = (Nuisance("y0", y0 - width / 2, width, bounded=True),) if width > 0 else ()
    return dataclasses.replace(seg, plant=plant, nuisance=nuisance, params=acting)


def _peaks(recording, plant) -> dict:
    """The largest command [V] a driven recording sent, and the armature current it could
    drive at rest [A] (None for a tap): where a limit's fit starts."""
    if recording.command is None or recording.kind == "tap":
        return {}
    top = float(np.max(np.abs(np.asarray(recording.command, dtype=float))))
    return {"command": top, "current": top / float(plant.Rm)}


# ---------------------------------------------------------------- the model


class _Layout(NamedTuple):
    """Static description of theta: which entries go where (hashable: a jit static)."""

    params: tuple[str, ...]  # canonical names, theta[0:len(params)] (logs)
    segments: tuple  # per segment: ((param name, index), ...), ((Nuisance, index), ...)
    substeps: int


def _positions(theta, data, smoothing, layout: _Layout):
    """Simulated positions of every segment, concatenated [m]."""
    out = []
    for (plant, controller, experiment, base), (params, nuisance) in zip(
        data, layout.segments, strict=True
    ):
        plant = plant.replace(
            **assemble(plant, {p: to_value(p, theta[i], jnp) for p, i in params}, jnp)
        )
        # The base values are data (a traced array), so that recordings differing only in them
        # share one compilation.
        values = {
            v.name: v._replace(base=base[j]).value(theta[i], jnp)
            for j, (v, i) in enumerate(nuisance)
        }
        experiment = dataclasses.replace(experiment, **values)
        res = simulate_smooth(
            plant, controller, experiment, smoothing=smoothing, substeps=layout.substeps
        )
        out.append(res.position)
    return jnp.concatenate(out)


def _residuals_jacobian(theta, data, measured, weight, smoothing, layout):
    """(r, dr/dtheta) of one theta: forward mode (a few parameters, many samples)."""
    TRACES[layout] = TRACES.get(layout, 0) + 1  # runs when traced, not when called

    def residuals(th):
        r = (_positions(th, data, smoothing, layout) - measured) * weight
        return r, r

    jac, r = jax.jacfwd(residuals, has_aux=True)(theta)
    return r, jac


_BATCHED: dict = {}
#: How often the residual function was traced, per layout (tests check it is once).
TRACES: dict = {}


def _batched_residuals(layout: _Layout):
    """``run(thetas (K, m), data, measured, weight, smoothing) -> (r (K, n), J (K, n, m))``:
    one compiled program per layout, sharded over the devices (:mod:`jaxcart.parallel`).
    The CPU's per-step loop overhead dominates a single run, so K trial points cost little more
    than one."""
    if layout not in _BATCHED:
        _BATCHED[layout] = sharded_map(
            partial(_residuals_jacobian, layout=layout), name="fit-residuals", static=layout
        )
    return _BATCHED[layout]


_positions_jit = jax.jit(_positions, static_argnames="layout")


class _Problem:
    """Segments, theta's layout and the compiled residual function."""

    def __init__(self, segments, params, settings: FitSettings, executor=None):
        self.segments = segments
        self.executor = executor or SERIAL
        self.params = tuple(canonical(p) for p in params)
        self.n_params = len(self.params)
        self.settings = settings
        index = len(self.params)
        layout = []
        theta = [to_theta(p, self._start_value(p)) for p in self.params]
        for k, seg in enumerate(segments):
            # A parameter free per recording maps to this recording's own copy (``v_sat@k``).
            own = [f"{p}@{k}" if f"{p}@{k}" in self.params else p for p in seg.params]
            ps = tuple((p, self.params.index(q)) for p, q in zip(seg.params, own, strict=True))
            nu = []
            for v in seg.nuisance:
                nu.append((v._replace(base=0.0), index))
                start = 0.0 if v.bounded else (getattr(seg.experiment, v.name) - v.base) / v.scale
                theta.append(float(start))
                index += 1
            layout.append((ps, tuple(nu)))
        self.layout = _Layout(self.params, tuple(layout), settings.substeps)
        # The name of every entry of theta: the parameters, then each segment's nuisances.
        self.entries = list(self.params) + [
            f"{v.name}@{k}" for k, seg in enumerate(segments) for v in seg.nuisance
        ]
        self.evaluations = 0  # smooth-model points evaluated (r and J)
        self.theta0 = np.asarray(theta, dtype=float)
        # Pad every segment to a multiple of PAD samples (weight 0 there): recordings of
        # nearly the same length then share one compiled residual function.
        self.sizes = [s.target.size for s in segments]
        self.observed = np.concatenate([s.target for s in segments])
        padded = [-(-n // PAD) * PAD for n in self.sizes]
        # On the device once: host leaves would be transferred again at every evaluation.
        self.data = jax.tree.map(
            put,
            tuple(
                (
                    s.plant,
                    s.controller,
                    _padded_experiment(s.experiment, n),
                    np.asarray([v.base for v in s.nuisance], dtype=float),
                )
                for s, n in zip(segments, padded, strict=True)
            ),
        )
        self.measured = put(
            np.concatenate(
                [
                    np.pad(s.target, (0, n - s.target.size))
                    for s, n in zip(segments, padded, strict=True)
                ]
            )
        )
        self.weight = put(
            np.concatenate(
                [
                    np.pad(np.ones(s.target.size), (0, n - s.target.size))
                    for s, n in zip(segments, padded, strict=True)
                ]
            )
        )
        self.rows = np.concatenate(
            [
                np.arange(n) + off
                for n, off in zip(self.sizes, np.cumsum([0, *padded[:-1]]), strict=True)
            ]
        )

    def _start_value(self, p) -> float:
        k, base = P.recording_of(p), base_name(p)
        segs = self.segments if k is None else [self.segments[k]]
        i = _element(p.split("@")[0])
        values = [
            float(s.plant.get(base) if i is None else s.plant.get(base)[i])
            for s in segs
            if base in s.params or p in s.params
        ]
        value = values[0] if values else _default_start(p.split("@")[0])
        if _log_scaled(p) and not value > 0:
            value = _default_start(p.split("@")[0])
        return value

    def start_source(self, p) -> str:
        """Where parameter ``p``'s start value comes from, in words (for a value held)."""
        base = base_name(p)
        declared = default_start().get(base)
        if base in plantspec.parameter_names() and plantspec.effect_of_param(base) is None:
            where = "the recordings' plant (the handout's appendix, a plant file or [plant])"
        elif declared is not None and math.isclose(
            self._start_value(p), declared if not isinstance(declared, tuple) else declared[0]
        ):
            where = "the effect's declared typical value"
        else:
            where = "the recordings' plant (a plant file, [plant] or --initial)"
        return f"its start value from {where}; give another with --initial {base}=VALUE"

    def smoothing(self, width) -> Smoothing:
        return Smoothing(voltage=self.settings.voltage_width, velocity=width, position=1e-6)

    def evaluate(self, theta, width):
        """(r, J) over the recorded samples, numpy float64; r = inf where the simulation is not
        finite."""
        th = put(theta, float)
        if th.size == 0:
            r = _positions_jit(th, self.data, self.smoothing(width), self.layout) - self.measured
            r = np.asarray(r)[self.rows]
            return r, np.zeros((r.size, 0))
        r, jac = self.evaluate_batch(th[None, :], width)
        return r[0], jac[0]

    def evaluate_batch(self, thetas, width):
        """(r (K, n), J (K, n, m)) of K points theta at once (one program, padded to
        :data:`LM_BATCH` points); r = inf for a point whose simulation is not finite."""
        thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
        k = thetas.shape[0]
        size = -(-k // LM_BATCH) * LM_BATCH
        padded = np.concatenate([thetas, np.repeat(thetas[-1:], size - k, axis=0)])
        self.evaluations += k
        r, jac = _batched_residuals(self.layout)(
            put(padded, float), self.data, self.measured, self.weight, self.smoothing(width)
        )
        r, jac = np.asarray(r)[:k, self.rows], np.asarray(jac)[:k, self.rows]
        bad = ~(np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(jac), axis=(1, 2)))
        r[bad] = np.inf
        return r, jac

    def segment_values(self, theta, k):
        """(plant values {name: value}, nuisance {name: value}) of segment k at theta."""
        params, _ = self.layout.segments[k]
        return (
            {p: float(to_value(p, theta[i])) for p, i in params},
            {v.name: float(v.value(theta[i])) for v, i in self.nuisance_index(k)},
        )

    def theta_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of every entry of theta: the plant's values inside what a cart of this
        lab has (engine.parameters.bounds), each bounded nuisance within +-BOUNDED_LIMIT (its
        sigmoid keeps a slope there), the other nuisances free."""
        low = np.full(self.theta0.size, -np.inf)
        high = np.full(self.theta0.size, np.inf)
        for i, name in enumerate(self.params):
            low[i], high[i] = (to_theta(name, b) for b in P.bounds(name))
        for k in range(len(self.segments)):
            for v, i in self.nuisance_index(k):
                if v.bounded:
                    low[i], high[i] = -BOUNDED_LIMIT, BOUNDED_LIMIT
        return low, high

    def clip_bounded(self, theta, reset=False):
        """theta within :meth:`theta_bounds`, with ``reset`` each bounded nuisance at 0, the
        middle of its range."""
        theta = np.clip(np.asarray(theta, dtype=float), *self.theta_bounds())
        if reset:
            for k in range(len(self.segments)):
                for v, i in self.nuisance_index(k):
                    if v.bounded:
                        theta[i] = 0.0
        return theta

    def nuisance_index(self, k):
        """((Nuisance with its base, index in theta), ...) of segment k."""
        idx = [i for _, i in self.layout.segments[k][1]]
        return tuple(zip(self.segments[k].nuisance, idx, strict=True))

    def simulate_exact(self, theta):
        """Exact-simulator positions of each segment at theta (list of arrays) [m]."""
        return self.simulate_exact_many([theta])[0]

    def simulate_exact_many(self, thetas):
        """:meth:`simulate_exact` at each of ``thetas``, the runs made several at a time
        (the executor's ``map``: several at a time)."""
        from tuning.estimation.engine.exact_runs import exact_position

        jobs = []
        for theta in thetas:
            for k, seg in enumerate(self.segments):
                values, nuisance = self.segment_values(theta, k)
                plant = seg.plant.replace(**assemble(seg.plant, values))
                jobs.append(
                    (plant, seg.controller, dataclasses.replace(seg.experiment, **nuisance))
                )
        runs = self.executor.map(exact_position, jobs, list(self.sizes) * len(thetas))
        n = len(self.segments)
        return [runs[i : i + n] for i in range(0, len(runs), n)]

    def exact_residuals(self, theta):
        """Exact-simulator positions minus the measured ones, all segments [m]."""
        return np.concatenate(self.simulate_exact(theta)) - self.observed

    def exact_available(self) -> bool:
        """True when the exact simulator models every effect of every segment's plant."""
        try:
            self.simulate_exact(self.theta0)
        except (ImportError, NotImplementedError):
            return False
        return True

    def split(self, r):
        """Per-segment parts of a vector over all samples."""
        return np.split(np.asarray(r), np.cumsum(self.sizes)[:-1])

    def split_rows(self, a):
        """Per-segment row blocks of a matrix over all samples."""
        return np.split(np.asarray(a), np.cumsum(self.sizes)[:-1], axis=0)


def _padded_experiment(experiment: Experiment, n: int) -> Experiment:
    """The experiment continued to n samples (its last signal value held)."""
    signal = np.asarray(experiment.signal, dtype=float)
    signal = np.pad(signal, (0, n - signal.size), mode="edge")
    return dataclasses.replace(experiment, signal=put(signal, float))


# ---------------------------------------------------------------- optimizers


def _exact_polish(problem, theta, active, jac, iterations):
    """Gauss-Newton on the exact simulator (:func:`~tuning.estimation.engine.exact_polish.
    gauss_newton`: residuals and forward-difference Jacobian both from
    :func:`jaxcart.exact.simulate_exact`), started from the smooth fit, in the internal
    coordinates (each entry moves at most MAX_STEP per iteration, as in the engine's
    :func:`~tuning.estimation.engine.lm.levenberg_marquardt`; a column the exact model's
    staircase flattens is a secant over +-STAIRCASE). Returns (theta,
    exact residuals, Jacobian with exact active columns, iterations, converged)."""
    # A bounded nuisance may have been pushed to its bound by the smooth model's own errors
    # (the breakaway lag); restart it from the middle, where the exact model decides.
    theta = problem.clip_bounded(theta, reset=True)
    idx = np.flatnonzero(active)
    jac = jac.copy()

    def full(x):
        out = theta.copy()
        out[idx] = x
        return out

    made = {}  # the Jacobian's columns, made at once (several at a time) by prefetch

    def residual(x):
        key = np.asarray(x, dtype=float).tobytes()
        if key in made:
            return made.pop(key)
        return problem.exact_residuals(full(x))

    def prefetch(xs):
        made.clear()
        for x, pos in zip(xs, problem.simulate_exact_many([full(x) for x in xs]), strict=True):
            made[np.asarray(x, dtype=float).tobytes()] = np.concatenate(pos) - problem.observed

    low, high = problem.theta_bounds()
    done = gauss_newton(
        residual,
        theta[idx],
        np.full(idx.size, 1e-6),  # internal units: a relative step of 1e-6 for the logs
        (low[idx], high[idx]),
        iterations,
        max_step=MAX_STEP,
        reference=np.linalg.norm(jac[:, idx], axis=0),
        staircase=STAIRCASE,
        prefetch=prefetch,
    )
    theta = theta.copy()
    theta[idx] = done.x
    if done.jac is not None:
        jac[:, idx] = done.jac
    return theta, done.r, jac, done.iterations, done.converged


# ---------------------------------------------------------------- the fit


def fit(
    recordings,
    params=("B_eq", "f_c"),
    *,
    per_recording=(),
    initial: dict | None = None,
    settings: FitSettings | None = None,
    exact: bool = True,
    progress: bool = True,
    executor=None,
) -> FitResult:
    """Fit plant parameters (shared by all recordings) and nuisance values (per recording).

    recordings: :class:`jaxcart.files.Recording` objects (or synthetic ones); params: names to
    fit (``B_eq``, ``f_c``, ``M``, ``gamma_scale``, ``v_sat`` alias ``v_limit``, or any plant
    parameter), all positive (fitted as logs); per_recording: those of ``params`` free in each
    recording they act in (a drive that differs from run to run: ``v_sat``, ``i_max``), fitted
    as ``name@k`` for recording ``k`` (:attr:`FitResult.per_recording`); the others are one
    value for every recording (the cart's mechanics); initial: starting (and, for names not
    fitted, fixed) values {name: value} [SI] applied to every recording's plant; exact: also
    run the exact simulator before and after; progress: a line per stage on stderr; executor:
    what makes the exact runs several at a time (a :class:`jaxcart.workers.Helpers` the caller
    owns; default: one after the other in this process). Returns a :class:`FitResult`; a
    parameter the data do not determine is reported as not identifiable and held at its
    starting value. Runs in float64 whatever jax_enable_x64 says.
    Refused before any fitting (:func:`jaxcart.plausibility.check_fit_recordings`): a
    recording without motion, the same data twice, an open-loop input in other units.
    """
    from jaxcart.plausibility import check_fit_recordings

    recordings = check_fit_recordings(recordings)
    with jax.enable_x64(True):
        return _fit(recordings, params, per_recording, initial, settings, exact, progress, executor)


#: Most Levenberg-Marquardt iterations of the direct start at the narrowest width (the
#: second candidate beside the continuation's; the P 50 step's needed 7).
DIRECT_ITERATIONS = 10


class _Run:
    """A fit's progress lines and the record of its optimizer runs."""

    def __init__(self, progress: bool):
        self.progress = progress
        self.stages: list = []
        self.history: list = []

    def say(self, text: str) -> None:
        if self.progress:
            print(f"fit: {text}", file=sys.stderr, flush=True)

    def stage(self, name, iterations, cap, converged) -> None:
        # Every optimizer run, so that one stopped at its iteration cap is reported.
        self.stages.append(
            {"stage": name, "iterations": iterations, "cap": cap, "converged": bool(converged)}
        )

    def lm(self, label, problem, theta, active, width, cap, tol=LM_TOLERANCE):
        """One Levenberg-Marquardt run, recorded and said; returns (theta, r, J)."""
        theta, r, jac, n_it, ok = levenberg_marquardt(problem, theta, active, width, cap, tol)
        self.stage(label, n_it, cap, ok)
        self.say(
            f"{label}: {n_it} iterations{'' if ok else ' (stopped at its cap)'}, "
            f"RMS {_rms(r) * 1e3:.4g} mm"
        )
        return theta, r, jac


def _fit(recordings, params, per_recording, initial, settings, exact, progress, executor):
    settings = settings or FitSettings()
    t_start = _time.perf_counter()
    params = parse_params(params)
    recordings = list(recordings)
    if not recordings:
        raise UserError("no recordings to fit; give at least one experiment file")
    values0 = {canonical(k): _initial_value(k, v) for k, v in (initial or {}).items()}
    segments = [prepare(rec, params, values0, settings) for rec in recordings]
    params = _expand(params, per_recording, segments)
    problem = _Problem(segments, params, settings, executor)
    run = _Run(progress)
    active, notes = _acting(problem)
    r0, _ = problem.evaluate(problem.theta0, settings.widths[-1])
    run.say(
        f"{len(segments)} recording(s), {r0.size} samples, fitting "
        f"{', '.join(params) or 'nothing'} (+{problem.theta0.size - problem.n_params} "
        f"nuisance); RMS before {_rms(r0) * 1e3:.4g} mm"
    )
    theta, r, jac = _optimize(problem, active, settings, run)
    exact = exact and problem.exact_available()

    def polish(theta, r, jac):
        if not exact:
            return theta, r, jac
        cap = settings.exact_iterations
        theta, r, jac, n_it, ok = _exact_polish(problem, theta, active, jac, cap)
        run.stage("Gauss-Newton on the exact simulator", n_it, cap, ok)
        run.say(
            f"exact simulator: {n_it} Gauss-Newton iterations"
            f"{'' if ok else ' (stopped at its cap)'}, RMS {_rms(r) * 1e3:.4g} mm"
        )
        return theta, r, jac

    theta, r, jac = polish(theta, r, jac)
    theta, r, jac, judged = _identify(problem, theta, r, jac, active, notes, settings, run, polish)
    result = _result(problem, params, values0, theta, r, judged, active, notes, run, exact)
    result = dataclasses.replace(result, seconds=_time.perf_counter() - t_start)
    # The warnings travel with the result (printed once, by whoever shows it).
    if exact:
        run.say(
            f"RMS after {result.rms_after * 1e3:.4g} mm (smooth), "
            f"{result.rms_after_exact * 1e3:.4g} mm (exact); {result.seconds:.1f} s"
        )
    return result


def _expand(params, per_recording, segments) -> tuple:
    """The fitted names: each parameter of ``per_recording`` as one copy per recording it acts
    in (``v_sat@1``), the others as given."""
    per = {canonical(n) for n in parse_params(per_recording)} if per_recording else set()
    missing = per - {canonical(p) for p in params}
    if missing:
        raise UserError(
            f"--per-recording {', '.join(sorted(missing))}: not among the fitted parameters; "
            "name it in --params too"
        )
    out = []
    for p in params:
        if canonical(p) in per:
            out += [
                f"{canonical(p)}@{k}" for k, s in enumerate(segments) if canonical(p) in s.params
            ]
        else:
            out.append(p)
    return tuple(out)


def _acting(problem) -> tuple[np.ndarray, dict]:
    """(active mask over theta, notes): a parameter that acts on no recording is held."""
    active = np.ones(problem.theta0.size, dtype=bool)
    notes: dict[str, str] = {}
    for i, name in enumerate(problem.params):
        k = P.recording_of(name)
        segs = problem.segments if k is None else [problem.segments[k]]
        if not any(name in s.params or base_name(name) in s.params for s in segs):
            active[i] = False
            notes[name] = "not identifiable: it does not act on these recordings"
    return active, notes


def _optimize(problem, active, settings, run):
    """The smooth fit: adam at the widest width, then Levenberg-Marquardt at each narrower
    width (the continuation), and the narrowest width straight from the start; the lower
    cost wins. Returns (theta, r, J)."""
    widths = tuple(settings.widths)
    narrow = widths[-1]
    theta = problem.theta0.copy()
    first = len(run.stages)
    r = jac = None
    for k, width in enumerate(widths):
        # Gradient descent where the model is smoothest, to leave a poor start; from there
        # Levenberg-Marquardt converges in a few iterations at each narrower width.
        steps = settings.adam_steps if k == 0 else 0
        theta, cost = adam(problem, theta, active, width, steps, settings.learning_rate)
        if cost is not None:
            rms = math.sqrt(cost / problem.observed.size)
            run.say(f"width {width:g} m/s: adam {steps} steps, RMS {rms * 1e3:.4g} mm")
        tol = LM_TOLERANCE if width == narrow else LM_TOLERANCE_WIDE
        label = f"Levenberg-Marquardt at width {width:g} m/s"
        theta, r, jac = run.lm(label, problem, theta, active, width, settings.lm_iterations, tol)
        if width != narrow:
            # A wider width only leads the way to the narrowest: its cap is no warning.
            run.stages[-1]["intermediate"] = True
        run.history.append((width, run.stages[-1]["iterations"], _rms(r)))
    if len(widths) == 1:
        return theta, r, jac
    # The continuation can lead astray where the wide widths change the physics: a closed
    # loop whose cart ends stuck short of the target creeps on under wide friction smoothing,
    # and B_eq takes up the friction (the built-in P 50 step, from f_c = 0.3 N, ended at
    # 1.5 mm RMS, 232 times the encoder floor, with B_eq 6 % high; straight from the start at
    # the narrowest width, 0.0043 mm and the truth). So the narrowest width is also fitted
    # straight from the start (at most DIRECT_ITERATIONS), and the lower cost there wins.
    cap = min(settings.lm_iterations, DIRECT_ITERATIONS)
    direct = levenberg_marquardt(problem, problem.theta0.copy(), active, narrow, cap, LM_TOLERANCE)
    # Lower by more than 1 %: where both find the same minimum, the continuation's stays.
    d, c = _rms(direct[1]), _rms(r)
    if not (math.isfinite(d) and (not math.isfinite(c) or d < 0.99 * c)):
        return theta, r, jac
    theta, r, jac, n_it, ok = direct
    # The continuation's result is discarded: its stages no longer judge the fit.
    for entry in run.stages[first:]:
        entry["superseded"] = True
    run.history[-1] = (narrow, n_it, _rms(r))
    run.stage(f"Levenberg-Marquardt at width {narrow:g} m/s from the start", n_it, cap, ok)
    run.say(
        f"width {narrow:g} m/s from the start: Levenberg-Marquardt {n_it} iterations"
        f"{'' if ok else ' (stopped at its cap)'}, RMS {_rms(r) * 1e3:.4g} mm: "
        "lower than the continuation's, kept"
    )
    return theta, r, jac


def _identify(problem, theta, r, jac, active, notes, settings, run, polish):
    """Identifiability: the worst determined parameter held at its start value and the rest
    refitted, until every relative standard error is within ``max_rel_stderr``. Returns
    (theta, r, J, (the engine's :class:`Covariance` over the active entries of theta in
    internal units, widened where the model misfits; the noise floor [m]; why the model
    misfits or ""))."""
    p = problem.n_params
    while True:
        idx = np.flatnonzero(active)
        names = [problem.entries[i] for i in idx]
        cov = covariance(problem.segments, names, None, jac[:, idx], problem.split(r))
        hac, singular = cov.robust, cov.singular
        # Relative standard errors (for log-scaled parameters the log-space error is that).
        rel = np.sqrt(np.diag(hac)) * np.asarray(
            [
                1.0
                if i >= p or _log_scaled(problem.params[i])
                else LINEAR_SCALE / max(abs(float(to_value(problem.params[i], theta[i]))), 1e-3)
                for i in idx
            ]
        )
        zero = np.linalg.norm(jac[:, idx], axis=0) == 0
        # Worst first: no effect at all, then the largest relative error, then the parameter
        # named last (the user lists the important ones first).
        bad = [
            (bool(zero[j]), math.inf if singular[j] or not rel[j] < math.inf else rel[j], j)
            for j, i in enumerate(idx)
            if i < p and (singular[j] or not rel[j] <= settings.max_rel_stderr)
        ]
        if not bad:
            break
        worst = max(bad)[2]
        i = int(idx[worst])
        name = problem.params[i]
        notes[name] = _why(name, worst, idx, hac, singular, zero, problem, theta)
        held_at = float(to_value(name, problem.theta0[i]))
        run.say(f"{name}: {notes[name]}; holding it at {held_at:.4g}, {problem.start_source(name)}")
        active[i] = False
        theta[i] = problem.theta0[i]
        label = f"Levenberg-Marquardt without {name}"
        narrow = settings.widths[-1]
        theta, r, jac = run.lm(label, problem, theta, active, narrow, settings.lm_iterations)
        theta, r, jac = polish(theta, r, jac)
    return theta, r, jac, _widened(problem, r, cov)


def _widened(problem, r, cov: Covariance) -> tuple:
    """(``cov`` with its standard errors widened where the model misfits, the noise floor [m],
    why the model misfits or "")."""
    floor = noise_floor(problem.segments)
    n_eff = effective_samples(problem.split(r))
    misfit = ""
    if misfits(_rms(r), floor):
        misfit = (
            f"the model does not explain the data: RMS {_rms(r) * 1e3:.3g} mm is "
            f"{_rms(r) / floor:.0f} times the encoder/noise level {floor * 1e3:.2g} mm; the "
            f"residual is worth {n_eff:.0f} independent samples of {r.size}, and the standard "
            "errors are widened to that; an effect may be missing (jaxcart diagnose)"
        )
        driven = sum(s.motor for s in problem.segments)
        if driven >= 2 and not any("@" in n for n in problem.params):
            misfit += (
                ", or the drive differs from run to run (--per-recording v_sat with v_sat in "
                "--params)"
            )
    return dataclasses.replace(cov, n_eff=n_eff, widened=bool(misfit)), floor, misfit


def _estimates(problem, params, theta, cov, active, notes) -> dict:
    """{name as asked: :class:`Estimate`} of every fitted parameter."""
    se_internal, se_naive = _errors(problem, cov)
    out = {}
    for asked, name in zip(params, problem.params, strict=True):
        i = problem.params.index(name)
        if active[i]:
            value = float(to_value(name, theta[i]))
            slope = P.value_slope(name, value)
            out[asked] = Estimate(
                asked,
                value,
                slope * float(se_internal[i]),
                stderr_naive=slope * float(se_naive[i]),
                edge=P.at_edge(name, value),
            )
        else:
            held = float(to_value(name, problem.theta0[i]))
            note = f"{notes[name]}; held at {held:.4g}, {problem.start_source(name)}"
            out[asked] = Estimate(asked, None, None, identifiable=False, note=note, held_at=held)
    return out


def _errors(problem, cov) -> tuple[dict, dict]:
    """({index in theta: standard error}, {index in theta: naive standard error}) of the
    entries of ``cov`` (internal units)."""
    idx = [problem.entries.index(n) for n in cov.names]
    naive = np.sqrt(np.diag(cov.naive))
    return dict(zip(idx, cov.stderrs(), strict=True)), dict(zip(idx, naive, strict=True))


def _correlation(problem, cov) -> dict:
    """{(a, b): correlation} of the identified plant parameters."""
    out = {}
    hac, idx = cov.robust, [problem.entries.index(n) for n in cov.names]
    ident = [j for j, i in enumerate(idx) if i < problem.n_params]
    for a in ident:
        for b in ident:
            if a < b:
                c = hac[a, b] / math.sqrt(hac[a, a] * hac[b, b])
                out[(problem.params[idx[a]], problem.params[idx[b]])] = float(c)
    return out


def _segment_fits(problem, theta, cov, exact, narrow) -> list:
    """A :class:`SegmentFit` per recording: before and after, smooth and exact, nuisances."""
    se_internal, se_naive = _errors(problem, cov)
    r0, _ = problem.evaluate(problem.theta0, narrow)
    before = problem.split(r0 + problem.observed)
    r_smooth, _ = problem.evaluate(theta, narrow)
    after = problem.split(r_smooth + problem.observed)
    before_exact = after_exact = [None] * len(problem.segments)
    if exact:
        before_exact = problem.simulate_exact(problem.theta0)
        after_exact = problem.simulate_exact(theta)
    out = []
    for k, seg in enumerate(problem.segments):
        pv, nv = problem.segment_values(theta, k)
        nuis = {}
        for v, i in problem.nuisance_index(k):
            slope = v.slope(theta[i])
            nuis[v.name] = Estimate(
                v.name,
                nv[v.name],
                float(se_internal.get(i, math.nan)) * slope,
                stderr_naive=float(se_naive.get(i, math.nan)) * slope,
            )
        plant = seg.plant.replace(**assemble(seg.plant, pv))
        fits = (before[k], after[k], before_exact[k], after_exact[k])
        out.append(SegmentFit(seg.name, seg.kind, seg.time, seg.target, *fits, nuis, plant))
    return out


def _result(problem, params, values0, theta, r, judged, active, notes, run, exact) -> FitResult:
    """The :class:`FitResult` of a finished fit (``seconds`` filled in by the caller)."""
    cov, floor, misfit = judged
    estimates = _estimates(problem, params, theta, cov, active, notes)
    values = {**values0}
    for seg in problem.segments:
        values.update(plant_values(seg.plant, [n for n in problem.params if "@" not in n]))
    per_run: dict = {}
    for i, name in enumerate(problem.params):
        if "@" in name:
            per_run.setdefault(base_name(name), []).append(float(to_value(name, theta[i])))
        else:
            values[name] = float(to_value(name, theta[i]))
    # The cart's plant holds a parameter free per recording at the median of its runs.
    values.update({n: float(np.median(v)) for n, v in per_run.items()})
    narrow = problem.settings.widths[-1]
    return FitResult(
        estimates,
        values,
        _segment_fits(problem, theta, cov, exact, narrow),
        _correlation(problem, cov),
        int(r.size),
        0.0,
        problem.smoothing(narrow),
        run.history,
        exact,
        run.stages,
        floor,
        cov.n_eff,
        misfit,
    )


def noise_floor(segments) -> float:
    """RMS position error [m] a correct model leaves on these segments (:func:`floor_of`)."""
    return floor_of((seg.target, seg.quantization) for seg in segments)


def _why(name, j, idx, cov, singular, zero, problem, theta) -> str:
    """Why parameter ``name`` (entry j of idx) is not identifiable, in one line."""
    i = int(idx[j])
    p = len(problem.params)
    if _log_scaled(name) and theta[i] < problem.theta0[i] - 8:  # shrunk 3000-fold: to zero
        return (
            f"not identifiable: the fit drives it towards 0 ({math.exp(theta[i]):.2g}); the "
            "data favour a model without it, or the model misses what they show"
        )
    if zero[j]:
        return "not identifiable: the data do not depend on it"
    if singular[j]:
        partners = [
            problem.params[idx[k]] for k in range(len(idx)) if k != j and idx[k] < p and singular[k]
        ]
        with_ = f" with {', '.join(partners)}" if partners else ""
        return f"not identifiable: the data depend on it only in a combination{with_}"
    rel = math.sqrt(cov[j, j])
    corr = []
    for k, i in enumerate(idx):
        if k != j and i < p:
            corr.append((abs(cov[j, k]) / math.sqrt(cov[j, j] * cov[k, k]), problem.params[i]))
    text = f"not identifiable: relative standard error {rel:.0%}"
    if corr:
        c, other = max(corr)
        if c > 0.9:
            text += f" (correlation {c:.3f} with {other})"
    return text


def cross_predict(
    values: dict,
    recordings,
    *,
    settings: FitSettings | None = None,
    progress: bool = False,
    executor=None,
) -> FitResult:
    """How well parameter ``values`` (e.g. ``FitResult.values`` of another recording) predict
    ``recordings``: only the nuisance values (a tap's start state) are fitted; the result's
    ``rms_after_exact`` is the prediction error [m]."""
    return fit(
        recordings, (), initial=values, settings=settings, progress=progress, executor=executor
    )


def _finite(x):
    """x as a float, or None where it is missing or not finite (JSON has no inf or nan)."""
    return float(x) if x is not None and math.isfinite(x) else None


def _rms(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else 0.0


# ---------------------------------------------------------------- fitted-plant files


def fit_table(result: FitResult, sources=()) -> dict:
    """What a fit knows, for a plant file's [fit] table: the structure fitted, every fitted
    parameter's value and standard error, the parameters held or not identifiable (the value
    held at, why), the RMS before and after and the noise floor [m], whether the model explains
    the data and the optimizers converged, the warnings, the recordings."""
    doc = result.to_json()
    fitted = {n: e for n, e in result.params.items() if e.identifiable and e.value is not None}
    held = {n: e.note for n, e in result.params.items() if not e.identifiable}
    table = {
        "structure": list(result.plant().structure) or ["nominal"],
        "fitted": [canonical(n) for n in fitted],
        "value": {canonical(n): e.value for n, e in fitted.items()},
        "stderr": {canonical(n): e.stderr for n, e in fitted.items()},
        "held": [canonical(n) for n in held],
        "held_at": {
            canonical(n): e.held_at
            for n, e in result.params.items()
            if not e.identifiable and e.held_at is not None
        },
        "why_held": {canonical(n): note or "" for n, note in held.items()},
        "rms_before": doc["rms_before"],
        "rms_after": doc["rms_after"],
        "noise_floor": result.noise_floor,
        "model_explains_data": not result.misfit,
        "converged": result.converged,
        "warnings": result.warnings,
        "recordings": [str(x) for x in sources],
    }
    return {k: v for k, v in table.items() if v is not None}


def write_fitted_plant(path, result: FitResult, *, sources=(), force: bool = False) -> Path:
    """Write the fitted plant as a plant file (TOML, :mod:`jaxcart.plantspec`) with a [fit]
    table (:func:`fit_table`); refuses to overwrite unless ``force``."""
    return plantspec.write_plant_file(
        path, result.plant(), fit=fit_table(result, sources), force=force
    )


def load_fitted_plant(path) -> Plant:
    """The plant of a plant file (written by ``jaxcart fit --out`` or ``diagnose``)."""
    return plantspec.read_plant_file(path)[0]


# ---------------------------------------------------------------- overlay plot


def plot_fit(result: FitResult, path, *, dpi: int = 130) -> Path:
    """Overlay of each recording and the model before and after the fit (exact simulator solid,
    smooth simulator dashed), with the residuals below; saves a PNG at ``path``."""
    from matplotlib.figure import Figure

    segs = result.segments
    fig = Figure(figsize=(8.0 * min(len(segs), 2) ** 0.5 + 1, 5.5), layout="constrained")
    axes = fig.subplots(2, len(segs), squeeze=False, sharex="col", height_ratios=(3, 2))
    for k, seg in enumerate(segs):
        ax, ax_r = axes[0, k], axes[1, k]
        t = seg.time
        ax.plot(t, seg.measured, color="black", lw=2.2, alpha=0.35, label="recorded")
        if seg.before_exact is not None:
            ax.plot(t, seg.before_exact, color="0.55", ls=":", lw=1.2, label="model before (exact)")
        else:
            ax.plot(t, seg.before, color="0.55", ls=":", lw=1.2, label="model before (smooth)")
        if seg.after_exact is not None:
            ax.plot(t, seg.after_exact, color="tab:blue", lw=1.2, label="fitted model (exact)")
        ax.plot(t, seg.after, color="tab:orange", ls="--", lw=1.2, label="fitted model (smooth)")
        ax.set_ylabel("position y [m]")
        ax.set_title(f"{seg.name} ({seg.kind}, {t[0]:.3f} to {t[-1]:.3f} s)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        if seg.after_exact is not None:
            ax_r.plot(
                t,
                (seg.after_exact - seg.measured) * 1e3,
                color="tab:blue",
                lw=1.0,
                label=f"exact, RMS {seg.rms_after_exact * 1e3:.3g} mm",
            )
        ax_r.plot(
            t,
            (seg.after - seg.measured) * 1e3,
            color="tab:orange",
            ls="--",
            lw=1.0,
            label=f"smooth, RMS {seg.rms_after * 1e3:.3g} mm",
        )
        ax_r.axhline(0.0, color="0.5", lw=0.6)
        ax_r.set_xlabel("time t [s]")
        ax_r.set_ylabel("model - recorded [mm]")
        ax_r.grid(alpha=0.3)
        ax_r.legend(fontsize=8, loc="best")
    fitted = ", ".join(
        f"{n} = {e.value:.4g} ± {e.stderr:.2g} {unit_of(n)}".rstrip()
        if e.identifiable
        else f"{n}: not identifiable"
        for n, e in result.params.items()
    )
    if not fitted:  # a prediction (cross_predict): show the values it ran with
        held = ", ".join(f"{n} = {v:.4g}" for n, v in result.values.items() if n in fittable())
        fitted = f"prediction with {held or 'the nominal plant'}"
    fig.suptitle(f"jaxcart fit: {fitted}", fontsize=11)
    from hw.atomicio import save_figure

    return save_figure(fig, path, dpi=dpi)
