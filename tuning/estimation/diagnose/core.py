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

from jaxcart.effects import REGISTRY
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.workers import SERIAL
from tuning.estimation.diagnose.policy import (
    K_MAX,
    MIN_COUNTS,
    MIN_SAMPLES,
    PENALTY_PER_EFFECT,
    PENALTY_PER_PARAM,
    PER_ROUND,
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
    #: Significance of each named effect or correction (z,
    #: :func:`~.significance.significance`) and why the structure is not eligible ("" when
    #: every part is significant), at ``assessed`` values.
    z: dict = field(default_factory=dict)
    why: dict = field(default_factory=dict)
    #: The parts whose every item is idle at ``assessed`` values (a correction within its
    #: margin, an effect under its least size: :func:`~.significance.significance`).
    idle: tuple = ()
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
