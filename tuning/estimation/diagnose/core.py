"""``diagnose``: where recordings and model part, which physics was left out, the model with it.

recordings -> segments (a tap: its coasting part; every position the middle of its count)
  -> controller check (a recorded command the file's PID does not reproduce: say so and
     infer the controller that ran, before any plant physics is blamed)
  -> round 1, one batch: baseline (B_eq), parameter errors (M, gamma_scale) and every
     single effect, each fitted through the smoothed simulator (one jit(vmap(LM)), widths
     wide -> narrow), re-checked on the exact simulator
  -> locate: windows of the baseline's exact residual beyond the encoder floor, regimes,
     residual tests
  -> round 2, one batch: pairs of the effects round 1 found (and each with Coulomb)
  -> round 3 (and on), one batch each, while the best structure is still above the misfit
     level and the score improves: forward selection, the best structures of the last round
     each with one more of the effects that helped (as many free slots as a pair)
  -> choice by an information criterion on the exact residual, floored at the encoder's
     own error, with a penalty per parameter and per added effect, among the structures whose
     every effect is significant (its strength beyond SIGNIFICANCE standard errors of the
     value where it does nothing, none at a bound); near-ties named
  -> exact polish of the choice, robust standard errors (widened for model error above the
     misfit level, as jaxcart fit does); the verdict says when no candidate explains the
     recording, when M and gamma_scale cannot be told apart, and which fitted values are
     physically implausible
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time as _time
from dataclasses import dataclass, field

import numpy as np

from jaxcart import plantspec
from jaxcart.effects import REGISTRY
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.workers import SERIAL
from tuning.estimation.diagnose.policy import (
    AT_BOUND,
    CORRECTION_MARGIN,
    K_MAX,
    MIN_COUNTS,
    MIN_SAMPLES,
    PENALTY_PER_EFFECT,
    PENALTY_PER_PARAM,
    PER_ROUND,
    RUN_SPREAD,
    SIGNIFICANCE,
    TIE,
)
from tuning.estimation.engine import parameters as P
from tuning.estimation.engine.batch import Layout
from tuning.estimation.engine.exact_polish import polish
from tuning.estimation.engine.exact_runs import ExactJob, exact_run, read_only
from tuning.estimation.engine.noise import repeatability
from tuning.estimation.engine.segments import recording_name

PARAM_ERRORS = {"mass": ("M",), "gain": ("gamma_scale",)}
#: The part that frees the drive's limits per recording: on several runs of one cart each run
#: has its own amplifier limit (the motor warms, the supply sags); the mechanics are shared.
PER_RUN = "per_run"


def effect_params() -> dict:
    """Effects a candidate adds, and the parameters it frees (B_eq is always free): every
    registered effect that is a candidate (``Effect.not_candidate``), as registered now."""
    return P.candidates()


def not_candidates() -> dict:
    """Registered effects that are not candidates, and why (each effect declares it)."""
    return {n: cls.not_candidate for n, cls in REGISTRY.items() if cls.not_candidate}


def per_run_params() -> tuple:
    """The parameters a PER_RUN structure frees per recording: those of the effects that
    limit the drive (``Effect.limits``)."""
    return tuple(p.name for n in effect_params() if REGISTRY[n].limits for p in REGISTRY[n].params)


def motor_only() -> set:
    """Parts that act only with the motor connected: effects of the drive alone, and the
    parameter corrections (a tap cannot tell M from B_eq)."""
    return {n for n in effect_params() if REGISTRY[n].drive_only()} | set(PARAM_ERRORS)


@dataclass
class Candidate:
    name: str
    parts: tuple  # effect or parameter-error names (and PER_RUN)
    free: tuple  # free parameter names (``name@i``: recording i's own value)
    values: dict = field(default_factory=dict)
    rms_smooth: float = math.nan
    rms_exact: float = math.nan
    score: float = math.nan
    window_evidence: float = math.nan
    residuals: list = field(default_factory=list)
    jac: object = None
    scale: float = 1.0
    round: int = 1
    #: Significance of each named effect or correction (z, :func:`significance`) and why the
    #: structure is not eligible ("" when every part is significant), at ``assessed`` values.
    z: dict = field(default_factory=dict)
    why: dict = field(default_factory=dict)
    assessed: object = None
    #: The values (:func:`values_key`) an exact polish converged at: one from them would
    #: repeat itself, so it is not run again.
    settled: object = None
    #: the recordings a PER_RUN part frees the drive limits of (driven runs)
    runs: tuple = ()
    #: (values key, the exact Jacobian there) of the held-out re-fits (crossval.exact_jacobian)
    jac_exact: tuple = (None, None)
    #: {"residuals": each recording's held-out prediction [m], "score"} at ``held_out_key``
    held: dict = field(default_factory=dict)
    held_out_key: object = None

    @property
    def why_not(self) -> str:
        return "; ".join(f"{k}: {v}" for k, v in self.why.items() if v)

    @property
    def effects(self) -> tuple:
        out = []
        for p in self.parts:
            if p in effect_params():
                out += list(P.named_by(p))
        return tuple(dict.fromkeys(out))

    @property
    def corrections(self) -> tuple:
        return tuple(p for p in self.parts if p in PARAM_ERRORS)

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "effects": list(self.effects),
            "parameter_corrections": [PARAM_ERRORS[p][0] for p in self.corrections],
            "free": list(self.free),
            "rms_smooth": self.rms_smooth,
            "rms": self.rms_exact,
            "score": self.score,
            "round": self.round,
            "significance": dict(self.z),
            "eligible": self.assessed is not None and not self.why_not,
            "why_not": self.why_not,
            "window_evidence": self.window_evidence,
            "values": {k: v for k, v in self.values.items() if "@" not in k},
            "per_recording": {
                k: v
                for k, v in self.values.items()
                if Layout.kind(k) in per_run_params() and "@" in k
            },
        }


# ---------------------------------------------------------------- preparing


def _excitation(rec, q) -> str | None:
    y = np.asarray(rec.position, dtype=float)
    name = recording_name(rec)
    if y.size < MIN_SAMPLES:
        return (
            f"{name}: too short to say anything ({y.size} samples, "
            f"{y.size * rec.sample_time:.3f} s); record at least {MIN_SAMPLES} samples of motion"
        )
    if not np.all(np.isfinite(y)):
        return f"{name}: column y has non-finite values; remove those rows"
    counts = np.ptp(y) / (q or ENCODER_RESOLUTION)
    if counts < MIN_COUNTS:
        return (
            f"{name}: no excitation: the cart moves {np.ptp(y) * 1e3:.3f} mm "
            f"({counts:.0f} encoder counts) in the whole recording; nothing to diagnose"
        )
    return None


# ---------------------------------------------------------------- candidates


def candidate_list(motor: bool, runs=(), coverage=None) -> list[Candidate]:
    """Round 1: the baseline, each correction and effect alone, and with two runs or more of
    a driven cart (``runs``: their recording indices) each drive limit free per run; an effect
    only where the recordings meet its data conditions (``coverage``, a
    :class:`~tuning.estimation.engine.coverage.Coverage`; None: every effect)."""
    out = [Candidate("baseline", (), ("B_eq",))]
    names = list(PARAM_ERRORS) + list(effect_params())
    for n in names:
        if n in motor_only() and not motor:
            continue
        if coverage is not None and n in REGISTRY and coverage.lacks(REGISTRY[n]):
            continue
        out.append(_structure((n,), runs))
    if len(runs) >= 2:
        out += [_structure((n, PER_RUN), runs) for n in effect_params() if REGISTRY[n].limits]
    return out


def pair(a: Candidate, b: Candidate) -> Candidate:
    return _structure(tuple(dict.fromkeys(a.parts + b.parts)), a.runs or b.runs)


# ---------------------------------------------------------------- exact re-check


def exact_plants(cand: Candidate, base_plants, values):
    """Each recording's plant at ``values``: the shared values, and a run's own copy of a
    parameter free per run (``v_sat@2``) where it has one."""
    from jaxcart.plantspec import build_plant

    named = {n: values[n] for n in cand.free if "@" not in n}
    named["B_eq"] = values["B_eq"]
    plants = []
    for i, p in enumerate(base_plants):
        own = {Layout.kind(k): v for k, v in values.items() if k.endswith(f"@{i}")}
        own = {k: v for k, v in own.items() if k in per_run_params()}
        if PER_RUN in cand.parts and not own:
            # A run without its own copy (a tap): the drive limits do not act there.
            own = {n: P.stand_in(n) for n in per_run_params() if n in _params_of(cand)}
        plants.append(build_plant(P.consistent({**named, **own}), base=p, check=False))
    return plants


def _params_of(cand) -> set:
    """The base names of the parameters ``cand`` frees."""
    return {Layout.kind(n) for n in cand.free}


class ExactMemo:
    """The last ``size`` exact runs of one diagnosis, by candidate structure and values: the
    polish re-runs points it has run (a trial it accepted is the next iteration's start, the
    polished point is re-checked), about a quarter of a diagnosis's exact runs (measured on
    the built-in P 50 step: 247 runs, 189 distinct). Results are shared: read-only arrays."""

    def __init__(self, size: int = 64, executor=None):
        self.size = size
        self.executor = executor or SERIAL  # makes the runs of fill several at a time
        self.runs: dict = {}
        self.hits = 0
        self.made = 0  # single runs simulated (here or by a helper process)
        # One recording's run by its own plant and start: a parameter that does not act on a
        # recording (a per-run copy of another run, a drive limit on the unplugged tap) leaves
        # its run as it was, so a forward difference re-simulates only the runs it moves.
        self.one: dict = {}

    def segment(self, key, compute):
        """One recording's exact run, by (index, plant, y0, yd0)."""
        if key in self.one:
            self.hits += 1
            self.one[key] = self.one.pop(key)
            return self.one[key]
        return self._store(key, compute())

    def fill(self, jobs) -> None:
        """Make the runs of ``jobs`` ((key, :class:`ExactJob`) pairs) not stored yet, all at
        once (the executor's ``map``: several at a time, in helper processes)."""
        todo = {}
        for key, job in jobs:
            if key not in self.one and key not in todo:
                todo[key] = job
        sizes = [job.target.size for job in todo.values()]
        for key, out in zip(todo, self.executor.map(exact_run, todo.values(), sizes), strict=True):
            self._store(key, out)

    def _store(self, key, out):
        self.made += 1
        self.one[key] = out = read_only(out)
        if len(self.one) > 4 * self.size:
            del self.one[next(iter(self.one))]
        return out

    def get(self, cand, values, compute):
        key = (
            tuple(cand.parts),
            tuple(cand.corrections),
            values_key(values),
        )
        if key in self.runs:
            self.hits += 1
            self.runs[key] = self.runs.pop(key)  # most recent last
            return self.runs[key]
        out = compute()
        for group in out:
            for a in group:
                if a is not None:
                    a.flags.writeable = False
        self.runs[key] = out
        if len(self.runs) > self.size:
            del self.runs[next(iter(self.runs))]
        return out


def exact_jobs(cand, segments, base_plants, values, layout) -> list:
    """(memo key, :class:`ExactJob`) of each recording of ``cand`` at ``values``."""
    plants = exact_plants(cand, base_plants, values)
    out = []
    for i, (seg, plant) in enumerate(zip(segments, plants, strict=True)):
        exp = seg.experiment
        if i in layout.nuisance:
            exp = dataclasses.replace(
                exp, y0=values.get(f"y0@{i}", exp.y0), yd0=values.get(f"yd0@{i}", exp.yd0)
            )
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


def _rms(parts) -> float:
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


# ---------------------------------------------------------------- exact polish + errors


def cost_to_reach(cand, reach, noise) -> float:
    """About the largest sum of squared residuals [m^2] at which ``cand`` scores ``reach`` or
    better (0 where its penalties alone score worse): every recording's share of it in
    proportion to its samples and floor (a screen, not a bound)."""
    at_floor = [np.full(int(n), f) for n, f in zip(noise.sizes, noise.floors, strict=True)]
    room = reach - score(cand, at_floor, noise)  # at the floor: the penalties alone
    floor_sse = float(np.sum(noise.sizes * noise.floors**2))
    return floor_sse * math.exp(min(room / noise.total, 700.0)) if room >= 0 else 0.0


def _polish(
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

    def residual(x):
        # Through the memo: a difference in a per-run value re-simulates its own run alone.
        parts = exact_residuals(cand, segments, base_plants, at(x), layout, memo)[0]
        return np.concatenate(parts) * rows

    def prefetch(xs):
        exact_prefetch(cand, segments, base_plants, [at(x) for x in xs], layout, memo)

    done = polish(
        residual, names, [values[n] for n in names], iterations,
        reference=smooth_reference(cand, names, values, segments),
        prefetch=prefetch if memo else None, target=target,
    )  # fmt: skip
    out = at(done.x) if done.improved else values
    jac = None if done.jac is None else done.jac / rows[:, None]  # the plain residual's
    return out, jac, names, done.converged


def values_key(values: dict) -> tuple:
    """``values`` as a key (names and floats, sorted)."""
    return tuple(sorted((k, float(v)) for k, v in values.items()))


def smooth_reference(cand, names, values, segments):
    """Column norms of ``cand``'s batch-fit Jacobian (its free slots, then the nuisances) per
    unit of each value of ``names`` (0 where it has none): where the smooth model sees a value
    act, a flat exact difference quotient is the staircase (the exact polish's ``reference``,
    :func:`~tuning.estimation.engine.exact_polish.polish`)."""
    slopes = np.array([P.value_slope(n, values[n]) for n in names])
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


def at_bound(name: str, value: float) -> str:
    """Which bound ("lower", "upper") ``value`` sits at, of :data:`~batch.BOUNDS` (within
    :data:`AT_BOUND`: relative for a parameter fitted as a logarithm, else a tenth of it as a
    share of the range); "" for none."""
    if Layout.kind(name) not in P.superset() and Layout.kind(name) not in P.NUISANCE:
        return ""
    lo, hi = P.bounds(name)
    if P.is_log(name):
        if value <= lo * math.exp(AT_BOUND):
            return "lower"
        if value >= hi * math.exp(-AT_BOUND):
            return "upper"
        return ""
    tol = 0.1 * AT_BOUND * (hi - lo)
    if value <= lo + tol:
        return "lower"
    if value >= hi - tol:
        return "upper"
    return ""


def _strengths(part, values, peaks, start):
    """Each item a part names: (item, its strength, the strength's weights for its standard
    error, what the strength measures, where the item does nothing). The strength is the
    distance from the values where the item does nothing, positive when it acts: each effect
    declares its own (``Effect.strengths``); a correction is its distance from the start
    plant's value beyond :data:`CORRECTION_MARGIN`."""
    if part in effect_params():
        for effect in P.named_by(part):
            yield from REGISTRY[effect].strengths(values, peaks)
    for name in PARAM_ERRORS.get(part, ()):
        was = start[name]
        yield (
            name,
            abs(values[name] - was) - CORRECTION_MARGIN * abs(was),
            {name: math.copysign(1.0, values[name] - was)},
            f"{name} = {values[name]:.4g}",
            f"{CORRECTION_MARGIN:.0%} of the start plant's {was:.4g}",
        )


def significance(parts, values, stderr, peaks=None, start=None) -> dict:
    """Is each effect (and parameter correction) of a structure there? A Wald test.

    parts: the structure's parts (:attr:`Candidate.parts`); values: its fitted values;
    stderr: ``f(weights) -> standard error`` of a linear combination of parameters
    (:meth:`~.engine.covariance.Covariance.stderr`); peaks: {"command": largest |command|
    sent [V], "current": largest |armature current| [A]} of the structure's own run
    (saturation, current limit);
    start: the start plant's M and gamma_scale.

    Each item's strength is its distance from the values where it does nothing: f_c from 0
    (Coulomb), f_s - f_c from 0 (stiction: static above kinetic), delay, deadzone and k_s from
    0, v_sat and i_max below the largest command and current of the run (a limit above them
    never acts), M and gamma_scale beyond :data:`CORRECTION_MARGIN` of the start plant's.
    z = strength / standard error; an item is significant when z > :data:`SIGNIFICANCE` and
    none of its part's parameters sits at a bound (:func:`at_bound`: the fit wanted a value
    beyond the range, its standard error means nothing). Returns {item: {"z", "why"}} ("why"
    empty when significant)."""
    peaks = peaks or {}
    start = start or {"M": 0.94, "gamma_scale": 1.0}
    out = {}
    for part in parts:
        if part == PER_RUN:
            out[PER_RUN] = _per_run_significance(values, stderr)
            continue
        params = effect_params().get(part) or PARAM_ERRORS.get(part, ())
        views = []
        for vals, pk, run in _views(params, values, peaks):
            bound = _bound_text(params, vals, per_run=run is not None)
            for item, strength, weights, what, neutral in _strengths(part, vals, pk, start):
                if run is not None:
                    weights = {_own(n, run, values): w for n, w in weights.items()}
                    what = f"{what} in run {run + 1}"
                z, why = _judge(item, strength, weights, stderr, what, neutral, bound)
                views.append((item, z, why))
        for item in dict.fromkeys(v[0] for v in views):
            # Of a part free per run, the run where it is clearest.
            mine = [v for v in views if v[0] == item]
            best = max(mine, key=lambda v: (not v[2], v[1] if math.isfinite(v[1]) else -math.inf))
            out[item] = {"z": float(best[1]), "why": best[2]}
    return out


def _own(name: str, run: int, values: dict) -> str:
    """``name@run`` where the run has its own copy of the parameter, else ``name``."""
    return f"{name}@{run}" if f"{name}@{run}" in values else name


def _views(params, values, peaks):
    """(values, peaks, run) to judge a part at: once, or once per run for a part whose
    parameters are free per run (each run's own values and its own largest command)."""
    runs = sorted({P.recording_of(k) for k in values if "@" in k and Layout.kind(k) in params})
    own = [i for i in runs if any(f"{n}@{i}" in values for n in params if n not in P.NUISANCE)]
    if not own:
        yield values, peaks, None
        return
    for i in own:
        vals = {**values, **{n: values[f"{n}@{i}"] for n in params if f"{n}@{i}" in values}}
        pk = {k: peaks.get(f"{k}@{i}", v) for k, v in peaks.items() if "@" not in k}
        yield vals, pk, i


def _bound_text(params, vals, per_run: bool) -> str:
    """Why a part's parameter at a bound makes it untestable ("" for none); a drive limit
    free per run may sit at its upper bound in a run it does not limit."""
    for n in params:
        side = at_bound(n, vals[n])
        if side and not (per_run and side == "upper"):
            return f"{n} = {vals[n]:.4g} sits at its {side} bound"
    return ""


def _judge(item, strength, weights, stderr, what, neutral, bound, gate=False) -> tuple[float, str]:
    """(z, why) of one item: its strength must act (be positive), be determined by the data
    (a standard error), and exceed the least size worth naming that its parameter declares
    (``Param.min_size``). z is the Wald statistic of the strength; with ``gate`` it must also
    exceed :data:`SIGNIFICANCE` (the drive limits' difference between runs). Whether an effect
    or a correction is there at all is decided by what it predicts (the search's selection by
    held-out prediction): a Wald test with standard errors widened for model error rejected
    Coulomb friction on a real P 50 step (z = 2.2) that predicts its end 2.6 times better."""
    se = stderr(weights)
    z = strength / se if se > 0 and math.isfinite(se) else math.nan
    if not math.isfinite(strength):
        z = math.inf if strength > 0 else math.nan
    least = _min_size(weights)
    if bound:
        return z, bound
    if not math.isfinite(z):
        return z, f"{what}: its standard error is not defined"
    if strength <= 0:
        idle = "is within" if item in P.CORRECTABLE else "does not act: not past"
        return z, f"{what} {idle} {neutral}"
    if gate and z <= SIGNIFICANCE:
        return z, f"{what} is {z:.1f} standard errors from {neutral} ({SIGNIFICANCE:g} needed)"
    if least and strength < least:
        return z, f"{what} is {strength:.3g} from {neutral}: under {least:g}, too small to matter"
    return z, ""


def _min_size(weights) -> float | None:
    """The least size worth naming of the strength's leading parameter, if it declares one."""
    name = Layout.kind(next(iter(weights)))
    try:
        return P.spec(name).min_size
    except KeyError:
        return None


def _per_run_inconsistency(values, peaks) -> str:
    """Why the drive limits free per run are more than one drive's spread ("" when they are
    not): a run's own limit below what another run of the same drive demonstrably drew (its own
    limit where it acts, else its largest command or current) by more than :data:`RUN_SPREAD`.
    Such a structure does not seed the forward selection, and where it is named for its
    held-out prediction the verdict says so."""
    for n in per_run_params():
        signal = next(REGISTRY[e].limits for e in effect_params() if n in effect_params()[e])
        own = {P.recording_of(k): v for k, v in values.items() if "@" in k and Layout.kind(k) == n}
        peak = {i: peaks.get(f"{signal}@{i}", math.inf) for i in own}
        acting = {i: v for i, v in own.items() if v < peak[i]}
        if len(own) < 2 or not acting:
            continue
        low = min(acting, key=acting.get)
        shown = {i: min(v, peak[i]) for i, v in own.items()}
        high = max(shown, key=shown.get)
        if shown[high] > RUN_SPREAD * acting[low]:
            unit, ratio = P.spec(n).unit, shown[high] / acting[low]
            return (
                f"run {low + 1}'s {n} is {ratio:.2g} times below what run {high + 1} drove "
                f"({signal} {shown[high]:.3g} {unit}): "
                f"more than one drive varies from run to run (at most {RUN_SPREAD:g} times): "
                f"run {low + 1} may show something the library does not model"
            )
    return ""


def _per_run_significance(values, stderr) -> dict:
    """Do the drive limits differ between runs? The largest difference between two runs' own
    values of a limit, as a Wald test (and beyond the limit's least size worth naming)."""
    best = {"z": math.nan, "why": "no drive limit is free per run"}
    for n in per_run_params():
        own = {P.recording_of(k): v for k, v in values.items() if "@" in k and Layout.kind(k) == n}
        if len(own) < 2:
            continue
        hi = max(own, key=own.get)
        lo = min(own, key=own.get)
        unit = P.spec(n).unit
        what = (
            f"{n} from {own[lo]:.3g} {unit} (run {lo + 1}) to {own[hi]:.3g} {unit} (run {hi + 1})"
        )
        z, why = _judge(
            PER_RUN,
            own[hi] - own[lo],
            {f"{n}@{hi}": 1.0, f"{n}@{lo}": -1.0},
            stderr,
            what,
            "the same value in every run",
            "",
            gate=True,
        )
        if math.isnan(best["z"]) or (not why and best["why"]) or z > best["z"]:
            best = {"z": z, "why": why}
    return best


def implausible(values: dict, free, track: float | None = None) -> list:
    """Lines for fitted values a real cart of this lab does not have: any free parameter at
    the edge of its plausible range or at a bound of its fit (:func:`at_bound`: the data ask
    for a value beyond it), a spring's rest point off the track. Such values are never
    written into a plant file (:func:`tuning.estimation.diagnose.report.write_outputs`)."""
    if track is None:
        from jaxcart.params import TRACK_LENGTH

        track = TRACK_LENGTH
    out = []
    for n in free:
        if n not in values or Layout.kind(n) in P.NUISANCE:
            continue
        v = values[n]
        unit = plantspec.unit(Layout.kind(n))
        unit = f" {unit}" if unit and unit != "1" else ""
        side = at_bound(n, v)
        rng = P.spec(n).plausible
        if side and rng is not None:
            out.append(
                f"{n} = {v:.4g}{unit} is outside what a cart of this lab has "
                f"({rng[0]:.3g}-{rng[1]:.3g}{unit}): the data ask for a value beyond it"
            )
        elif side:
            out.append(
                f"{n} = {v:.4g}{unit} sits at its {side} bound (the fit wanted a value "
                "beyond its range)"
            )
        elif P.spec(n).unit == "m" and P.spec(n).neutral is None and abs(v) > track / 2:
            out.append(f"{n} = {v:.4g} m is off the {track:g} m track")
    return out


def swapped_correction(parts, values, plant):
    """The structure with the other of M and gamma_scale, and the values that give the same
    motion: the cart obeys y'' + (c/m) y' = (gamma/m) v + F/m, so with B_eq free a closed loop
    fixes only gamma/m, c/m and every force over m (c = B_eq + B_emf, m = M + M_J, B_emf and
    M_J from the motor's constants). Returns (parts, values) or None (one correction needed;
    None also when the equivalent B_eq or M is not positive: then the two differ)."""
    corr = [p for p in parts if p in PARAM_ERRORS]
    if len(corr) != 1 or not plant.motor_connected:
        return None
    m_j, b_emf = float(plant.M_J), float(plant.B_emf)
    m0, g0 = float(plant.M), float(plant.gamma_scale)
    new = {k: v for k, v in values.items() if k not in ("M", "gamma_scale")}
    if corr[0] == "mass":
        k = (m0 + m_j) / (values["M"] + m_j)  # m_new / m_old
        new["gamma_scale"] = g0 * k
        swap = "gain"
    else:
        k = g0 / values["gamma_scale"]
        new["M"] = (m0 + m_j) * k - m_j
        swap = "mass"
        if new["M"] <= 0:
            return None
    new["B_eq"] = (values["B_eq"] + b_emf) * k - b_emf
    if new["B_eq"] <= 0:
        return None
    for n in ("f_c", "f_s", "k_s"):
        if n in new:
            new[n] = values[n] * k
    return tuple(swap if p == corr[0] else p for p in parts), new


def extend(seeds, additions, seen, kmax=K_MAX, limit=PER_ROUND) -> list:
    """Forward selection: each seed structure with one more addition (a single structure),
    at most ``kmax`` free parameters (the batch's slots) and one parameter correction, not in
    ``seen`` (sets of parts; updated), Coulomb and stiction not both (stiction holds Coulomb),
    at most ``limit`` of them, by the sum of the seed's and the addition's ranks (the best
    seed first among equals). Returns [(candidate, seed, addition)]."""
    ranked = sorted(
        ((i + j, i, a, b) for i, a in enumerate(seeds) for j, b in enumerate(additions)),
        key=lambda t: t[:2],
    )
    out = []
    for _, _, a, b in ranked:
        c = pair(a, b)
        parts = frozenset(c.parts)
        if (
            parts in seen
            or len(c.parts) == len(a.parts)
            or len(c.free) > kmax
            or P.redundant(parts)
            or len([p for p in c.parts if p in PARAM_ERRORS]) > 1
        ):
            continue
        seen.add(parts)
        out.append((c, a, b))
        if len(out) >= limit:
            break
    return out


# ---------------------------------------------------------------- the diagnosis


def _progress_printer(progress):
    if progress is True:
        return lambda text: print(text, file=sys.stderr, flush=True)
    if callable(progress):
        return progress
    return lambda text: None


def _theta_jacobian(cand, jac, order, values, nuis, segments) -> np.ndarray:
    """The exact re-fit's forward-difference Jacobian (columns in ``order``, per unit of each
    value) in the form of the batch fit's: columns the candidate's free slots and the
    nuisances, per unit of the fitted parameter (its logarithm for a log-fitted one), times
    :func:`fitter_scale`. An empty array where the re-fit made none or lacks a column."""
    names = list(cand.free) + list(nuis)
    if jac is None or any(n not in order for n in names):
        return np.zeros((0, 0))
    cols = [jac[:, order.index(n)] * P.value_slope(n, values[n]) for n in names]
    return fitter_scale(segments) * np.column_stack(cols)


def _misfits(rms, floor) -> bool:
    from tuning.estimation.engine.noise import misfits

    return misfits(rms, floor)


def _pair_starts(grown, starts_all, base) -> list:
    """Start values of combined structures: the seed's fitted values over the addition's over
    the defaults. A structure that scores worse than the ``base``line it nests has not fitted
    (the real P 50 run: Coulomb alone ends at f_c 2.9 N and 9.9 mm, the baseline at 8.2 mm),
    and its values are not a start (from them saturation + Coulomb stays at 9.9 mm; from the
    saturation's values and f_c's start it reaches 1.19 mm)."""
    starts = []
    for c, a, b in grown:
        s = {k: starts_all[Layout.kind(k)] for k in c.free}
        for fitted in (b, a):
            if fitted.score <= base.score:
                s.update({k: v for k, v in fitted.values.items() if k in c.free})
        starts.append(s)
    return starts


def _counts_in_loop(base_plants, segments, read_counts) -> tuple[list, list]:
    """(base plants, segments), with the encoder's quantization in the loop where the recorded
    command shows that the controller read the recorded counts (``read_counts``, one per
    recording: controller.reads_counts), unless the plant models its sensor already.

    Feeding the controller the exact position instead biases its input by half a count (the
    mean of the floor) and loses the hunting between counts that integral action and friction
    make, which the search otherwise explains with effects that are not there. Such a
    simulation records what its controller read, whole counts; the diagnosis compares the
    cart's position instead (:func:`exact_residuals`), whose forward differences the exact
    polish needs (docs/diagnose.md, "The encoder in the loop")."""
    from jaxcart.plantspec import build_plant

    plants, segs = [], []
    for plant, seg, counts in zip(base_plants, segments, read_counts, strict=True):
        q = seg.quantization
        sensor, count = P.encoder()
        modelled = sensor in plant.structure  # a plant file's own sensor
        if counts and q > 0 and not modelled:
            plant = build_plant({count: q}, base=plant, check=False)
        if q > 0 and (modelled or counts):
            seg = dataclasses.replace(seg, counts_in_loop=True)
        plants.append(plant)
        segs.append(seg)
    return plants, segs


def _current_peaks(cand, segments, base_plants, values, layout) -> dict:
    """Largest |armature current| [A] of each motor segment's exact run under ``cand``,
    i = (v - (B_emf/gamma) y')/Rm at the samples: {segment index: peak}."""
    from jaxcart.exact import simulate_exact

    peaks = {}
    plants = exact_plants(cand, base_plants, values)
    for i, (seg, plant) in enumerate(zip(segments, plants, strict=True)):
        if not seg.motor:
            continue
        exp = seg.experiment
        if i in layout.nuisance:
            exp = dataclasses.replace(
                exp, y0=values.get(f"y0@{i}", exp.y0), yd0=values.get(f"yd0@{i}", exp.yd0)
            )
        res = simulate_exact(plant, seg.controller, exp)
        k_b = float(plant.B_emf) / float(plant.gamma)
        i_arm = (np.asarray(res.voltage) - k_b * np.asarray(res.velocity)) / float(plant.Rm)
        peaks[i] = float(np.nanmax(np.abs(i_arm))) if np.any(np.isfinite(i_arm)) else 0.0
    return peaks


def _cart_plant(best, base_plants, segments, peaks):
    """The cart's plant of ``best`` (the first driven run's); a drive limit free per run at
    the median of the runs' values where it acts (:func:`_acts`: above what a run drove, its
    value is not determined), each run's own in the per-recording results."""
    # no run's own copy: exact_plants would give the first driven run its own, not the median
    values = {
        k: v
        for k, v in best.values.items()
        if "@" not in k or Layout.kind(k) not in per_run_params()
    }
    for n in per_run_params():
        own = {k: v for k, v in best.values.items() if "@" in k and Layout.kind(k) == n}
        acting = [v for k, v in own.items() if _acts(n, k, v, peaks)]
        if own:
            values[n] = float(np.median(acting or list(own.values())))
    cand = _structure(tuple(p for p in best.parts if p != PER_RUN))
    plants = exact_plants(cand, base_plants, values)
    motor = [p for p, s in zip(plants, segments, strict=True) if s.motor]
    return motor[0] if motor else plants[0]


def _repeat_levels(segments) -> dict:
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


def _remainder(best, segments) -> str:
    """The best structure's residual in words, on the segment where most of it is left."""
    from tuning.estimation.diagnose import locate

    k = max(range(len(segments)), key=lambda i: float(np.sum(best.residuals[i] ** 2)))
    text = locate.describe_residual(best.residuals[k], float(segments[k].experiment.sample_time))
    return text + (f" (in {segments[k].name})" if len(segments) > 1 else "")


def _acts(name, key, value, peaks) -> bool:
    """Whether drive limit ``name``'s value in run ``key`` (``i_max@2``) is below what that run
    drove (``peaks``' ``{command,current}@i``), so that it acts (any other value: True)."""
    signal = next((REGISTRY[e].limits for e in effect_params() if name in effect_params()[e]), "")
    return not signal or value < peaks.get(f"{signal}@{P.recording_of(key)}", math.inf)


def _per_recording(best, names, segments, base, cov, peaks) -> dict:
    """{recording name: {"parameters": its own values ("acts": False for a limit above what
    that run drove: {command,current}@i of ``peaks``), "rms_before", "rms_after" [m]}}."""
    out = {}
    for i, (name, seg) in enumerate(zip(names, segments, strict=True)):
        own = {}
        for k in best.free:
            if k.endswith(f"@{i}") and Layout.kind(k) not in P.NUISANCE:
                n = Layout.kind(k)
                own[n] = {
                    "value": best.values[k],
                    "stderr": cov.stderr({k: 1.0}),
                    "unit": P.spec(n).unit,
                    "acts": _acts(n, k, best.values[k], peaks),
                }
        if names.count(name) > 1:  # recordings of one name told apart by their place
            name = f"{name} #{i + 1}"
        out[name] = {
            "kind": seg.kind,
            "parameters": own,
            "rms_before": _rms([base.residuals[i]]),
            "rms_after": _rms([best.residuals[i]]),
        }
    return out


def _items(part) -> tuple:
    """The items a part names (:func:`significance`'s keys)."""
    if part == PER_RUN:
        return (PER_RUN,)
    return PARAM_ERRORS.get(part) or P.named_by(part)


def _structure(parts, runs=()) -> Candidate:
    """The candidate of ``parts``: B_eq and each part's parameters free; with :data:`PER_RUN`
    among them, each drive limit's value free per run of ``runs`` instead of shared."""
    free = ["B_eq"]
    for p in parts:
        free += list(effect_params().get(p) or PARAM_ERRORS.get(p, ()))
    if PER_RUN in parts:
        free = [
            x for n in free for x in ([f"{n}@{i}" for i in runs] if n in per_run_params() else [n])
        ]
    return Candidate("+".join(parts), tuple(parts), tuple(dict.fromkeys(free)), runs=tuple(runs))


def without_part(parts, part) -> tuple:
    """``parts`` without ``part``, keeping what it stands on (``Effect.requires``): Stribeck
    friction without its fall is stiction, not the baseline."""
    rest = [p for p in parts if p != part]
    for r in REGISTRY[part].requires if part in REGISTRY else ():
        standing = rest + [x for x in REGISTRY[part].requires if x != r]
        if r not in rest and not any(r in REGISTRY[q].requires for q in standing if q in REGISTRY):
            rest.append(r)
    return tuple(rest)


def _swap_tie(best, cands, plant, segments, base_plants, layout, memo, noise):
    """({}, None), or when ``best`` corrects M or gamma_scale and the structure with the other
    (values from :func:`swapped_correction`, or its own fit where that scores better) is
    within :data:`TIE`: the facts for the verdict and that structure."""
    swap = swapped_correction(best.parts, best.values, plant)
    if swap is None:
        return {}, None
    parts, values = swap
    other = _structure(parts, best.runs)
    keys = list(other.free) + [k for k in best.values if "@" in k]
    other.values = {k: values[k] for k in keys}
    other.residuals = exact_residuals(other, segments, base_plants, other.values, layout, memo)[0]
    other.rms_exact = _rms(other.residuals)
    other.score = score(other, other.residuals, noise)
    fitted = next((c for c in cands if set(c.parts) == set(parts)), None)
    if fitted is not None and fitted.score < other.score:
        other = fitted
    if not other.score <= best.score + TIE:
        return {}, None
    pm = plant_of(best, base_plants, segments)
    ratios = {"gamma/m": float(pm.gamma / pm.m), "c/m": float(pm.c / pm.m)}
    corr = {c.corrections[0]: c for c in (best, other)}
    mass, gain = corr["mass"], corr["gain"]
    b_eq = sorted([best.values["B_eq"], other.values["B_eq"]])
    note = (
        "M and gamma_scale cannot be told apart from "
        + ("this recording" if len(segments) == 1 else "these recordings")
        + f": with B_eq free only gamma/m = {ratios['gamma/m']:.4g} N/(V kg) and c/m = "
        f"{ratios['c/m']:.4g} 1/s are identifiable (M = {mass.values['M']:.4g} kg with "
        f"B_eq = {mass.values['B_eq']:.4g} kg/s, or gamma_scale = "
        f"{gain.values['gamma_scale']:.4g} with B_eq = {gain.values['B_eq']:.4g} kg/s, fit "
        "equally well), so B_eq is not settled; diagnose a tap of the same cart with it "
        "(jaxcart diagnose RUN.toml TAP.toml) to separate them"
    )
    facts = {
        "parameters": ["M", "gamma_scale"],
        "ratios": ratios,
        "alternatives": [
            {
                "structure": c.name,
                "values": {k: v for k, v in c.values.items() if "@" not in k},
                "rms": c.rms_exact,
                "score": c.score,
                "implausible": implausible(c.values, c.free),
            }
            for c in (best, other)
        ],
        "B_eq": b_eq,
        "note": note,
    }
    return facts, other


def plant_of(cand, base_plants, segments):
    """The plant of ``cand`` at its values (the first motor segment's)."""
    plants = exact_plants(cand, base_plants, cand.values)
    motor = [p for p, s in zip(plants, segments, strict=True) if s.motor]
    return motor[0] if motor else plants[0]


#: What a residual that still correlates with each signal after the best structure may point
#: to beyond the candidates (the suggestions of a diagnosis that explains nothing).
BEYOND = {
    "position": "a force that varies along the track (track_friction, not a candidate: "
    "jaxcart fit --params B_eq,f_track)",
    "sign_velocity": "friction beyond Coulomb and stiction (speed-dependent, Stribeck) or "
    "backlash (jaxcart fit --params B_eq,backlash)",
    "command": "a drive nonlinearity beyond saturation, deadzone and current limit",
    "acceleration": "inertia or lag beyond M and delay (the motor's electrical lag)",
}


def _suggestions(tests, best) -> list:
    """What may be missing when nothing explains the recording: the signals the best
    structure's residual still correlates with (:data:`BEYOND`), more effects at once,
    physics outside the library."""
    out = [
        BEYOND[k] + f" (its residual correlates with {k.replace('_', ' ')}, z = {t['z']:+.0f})"
        for k, t in tests.items()
        if k in BEYOND and t.get("significant")
    ]
    n = len(best.free) - 1
    out.append(
        f"more effects at once than the search combines ({n} parameters here, at most {K_MAX - 1})"
        if n >= K_MAX - 2
        else "more effects at once"
    )
    out.append("physics outside the effects library")
    return out


def _spread(processes, items, compute):
    """``[compute(item) for item in items]``, each a ({name: float}, [arrays]) pair; with
    ``processes`` (a :class:`tuning.distributed.Exchange`) each item computed by one process and
    every result gathered on every process."""
    if processes is None:
        return [compute(item) for item in items]
    mine = {}
    for i in processes.items(len(items)):
        values, arrays = compute(items[i])
        mine[f"n/{i}"] = np.array(len(arrays))
        mine[f"k/{i}"] = np.array(list(values), dtype=str)
        mine[f"v/{i}"] = np.array([values[k] for k in values], dtype=float)
        mine.update({f"a/{i}/{j}": a for j, a in enumerate(arrays)})
    every = {k: v for part in processes.allgather(mine) for k, v in part.items()}
    out = []
    for i in range(len(items)):
        keys, vals = every[f"k/{i}"], every[f"v/{i}"]
        values = {str(k): float(v) for k, v in zip(keys, vals, strict=True)}
        out.append((values, [every[f"a/{i}/{j}"] for j in range(int(every[f"n/{i}"]))]))
    return out


def fitter_scale(segments) -> float:
    return 1.0 / math.sqrt(sum(s.target.size for s in segments))


def _window_evidence(cands, base, masks) -> None:
    """How much of the located windows' residual energy each candidate removes (0..1)."""
    base_w = sum(float(r[m] @ r[m]) for r, m in zip(base.residuals, masks, strict=True))
    for c in cands:
        cw = sum(float(r[m] @ r[m]) for r, m in zip(c.residuals, masks, strict=True))
        c.window_evidence = 1.0 - cw / base_w if base_w > 0 else 0.0


def _window_masks(segments, wins):
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


def _fmt_list(costs, fitter) -> str:
    scale = fitter_scale(fitter.segments)
    del scale
    return " ".join(f"{math.sqrt(max(c, 0.0)) * 1e3:.3f}" for c in costs) + " mm"


def _elapsed(t0) -> float:
    return round(_time.perf_counter() - t0, 2)
