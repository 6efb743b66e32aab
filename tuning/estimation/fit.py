"""Fit plant parameters to recordings: gradient through the smoothed simulator, a
Levenberg-Marquardt polish, a last Gauss-Newton polish on the exact simulator, standard errors
that survive autocorrelated residuals, and identifiability.

    recordings --fit_segment--> segments (a tap: its coasting part, found automatically;
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
from dataclasses import dataclass

import jax
import numpy as np

from jaxcart import plantspec
from jaxcart.errors import UserError
from jaxcart.plausibility import check_fit_recordings
from jaxcart.smoothing import continuation
from tuning.estimation.engine import parameters, smooth_runs, starts
from tuning.estimation.engine.covariance import Covariance, covariance
from tuning.estimation.engine.exact_polish import polish
from tuning.estimation.engine.least_squares import (
    LM_DAMPING,
    LM_TOLERANCE,
    LM_TOLERANCE_WIDE,
    MAX_STEP,
    adam,
    levenberg_marquardt,
    minimize,
)
from tuning.estimation.engine.noise import (
    effective_samples,
    encoder_count,
    floor_of,
    misfits,
    noise_level,
)
from tuning.estimation.engine.parameters import base_name
from tuning.estimation.engine.segments import Segment, counts_in_loop
from tuning.estimation.engine.segments import prepare as prepare_segment
from tuning.estimation.fitting.files import fit_table, load_fitted_plant, write_fitted_plant
from tuning.estimation.fitting.model import Nuisance, _Problem
from tuning.estimation.fitting.names import (
    _drives_nothing,
    _initial_value,
    canonical,
    default_start,
    fittable,
    not_fitted,
    parse_params,
    plant_values,
    unit_of,
    with_values,
)
from tuning.estimation.fitting.plot import plot_fit
from tuning.estimation.fitting.result import Estimate, FitResult, SegmentFit, _rms

#: The public entry: ``jaxcart fit``'s functions and types, wherever they are written.
__all__ = [
    "Estimate", "FitResult", "FitSettings", "Nuisance", "SegmentFit", "canonical",
    "cross_predict", "default_start", "fit", "fit_table", "fittable", "load_fitted_plant",
    "not_fitted", "parse_params", "plant_values", "plot_fit", "fit_segment",
    "unit_of", "with_values", "write_fitted_plant"
]  # fmt: skip


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

    @classmethod
    def warm(cls) -> FitSettings:
        """A fit that starts near its answer (a lab part from an earlier part's values, a
        fold of a joint fit from the joint values): no adam, the last two widths of the
        continuation, a short Levenberg-Marquardt at each."""
        return cls(widths=cls().widths[-2:], adam_steps=0, lm_iterations=15)

    @classmethod
    def exact_only(cls) -> FitSettings:
        """A fit that starts at a neighbouring fit's answer (the lab's driven runs alone from
        the joint fit of every recording): the exact polish alone, the smooth model's
        Jacobian at the start (narrowest width) its reference. The smooth stages of
        :meth:`warm` lead away from an exact optimum to the smooth model's, and the polish back
        (on a generated student's five driven runs: 4.5 s against the warm fit's 7.5 s in one
        process, the values within 0.003 standard errors of its)."""
        return cls(widths=cls().widths[-1:], adam_steps=0, lm_iterations=0)


def fit_segment(recording, params, values: dict, settings: FitSettings) -> Segment:
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
    declared = default_start()
    for p in canon:  # a fitted effect the plant lacks starts where it acts on these data
        b = base_name(p)
        if b in declared and b not in plant.param_names() and not _drives_nothing(b, plant):
            start = (
                declared[b]
                if plantspec.param(b).size
                else parameters.start_for(b, peaks, raw.mean())
            )
            plant = with_values(plant, {b: start})
    acting = tuple(p for p in canon if base_name(p) in plant.param_names())
    # A plant that models its encoder (quantization in [plant] or a plant file): its controller
    # reads the counts, and the cart's own position is compared, as the diagnosis does (the
    # counts' staircase gave a Jacobian only at the count edges: standard errors 200 times too
    # small, the optimizer at its cap). Counts the plant does not name are not added here: see
    # docs/diagnose.md, "The encoder in the loop".
    (plant,), (seg,) = counts_in_loop([plant], [seg], [False])
    if seg.kind == "tap":
        nuisance = (
            Nuisance("y0", 0.0, parameters.NUISANCE["y0"][0]),
            Nuisance("yd0", 0.0, parameters.NUISANCE["yd0"][0]),
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


# ---------------------------------------------------------------- optimizers


def _levenberg_marquardt(problem, theta, active, width, iterations, tolerance=LM_TOLERANCE):
    """The engine's :func:`~tuning.estimation.engine.least_squares.levenberg_marquardt` on the
    active entries of theta (internal units) of the smooth fit ``problem``: the dampings
    :data:`LM_DAMPING` tried in one batched evaluation per iteration, each entry's step at most
    MAX_STEP (an e-fold of a parameter, 1 mm of y0: far from the optimum the Gauss-Newton step
    can throw a log-parameter to where the data no longer depend on it), converged when a step
    moves the parameters by under ``tolerance`` of a standard error that the residual supports
    (:func:`effective_samples`), or no step lowers the cost. Returns (theta, r, J, iterations
    done, converged)."""
    r, jac = problem.evaluate(theta, width)
    if not math.isfinite(float(r @ r)):
        raise UserError(
            "the model does not simulate at the starting values (not finite); "
            "give starting values closer to the cart's (a plant file, --plant FILE, or the "
            "recording's [plant] table); where a warning above says a column is in other "
            "units, fix that first"
        )
    if not np.any(active):
        return theta, r, jac, 0, True
    solver = levenberg_marquardt(
        dampings=LM_DAMPING,
        shrink=5.0,
        damping_range=(1e-12, 1e10),
        give_up=True,
        bounds=problem.theta_bounds(),
        max_step=MAX_STEP,
        # A nuisance's step may be cut without holding convergence back.
        trusted=active & (np.arange(theta.size) < problem.n_params),
        # Near the minimum d cost = sum (d theta / stderr)^2 sigma^2 N / n_eff (the stderr that
        # n_eff independent samples support, of the current residual, which whitens as the
        # fit improves).
        tolerance=lambda r: tolerance**2 * problem.cost_per_variance(r),
        free=active.astype(float),
        objective=problem.objective,
    )
    state = minimize(
        solver,
        lambda trials: problem.evaluate_batch(trials, width),
        solver.init(theta, r, jac),
        iterations,
    )
    return state.x, state.r, state.jac, int(state.iterations), bool(state.converged)


def _exact_polish(problem, theta, active, jac, iterations):
    """The engine's exact polish (:func:`~tuning.estimation.engine.exact_polish.polish`:
    Gauss-Newton, residuals and forward-difference Jacobian both from
    :func:`jaxcart.exact.simulate_exact`), started from the smooth fit, in the internal
    coordinates (each entry moves at most MAX_STEP per iteration, as in the engine's
    :func:`_levenberg_marquardt`; a column the exact model's
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

    # Several recordings: each weighed as at the smooth fit's answer (the joint objective's
    # reweighted least squares, problem.objective).
    rows = None
    if problem.noise is not None:
        weights = problem.row_weights(problem.split(problem.exact_residuals(theta)))
        rows = np.sqrt(weights) if np.all(weights > 0) else None  # none runs away

    def residuals(xs):  # the points' runs made at once, several at a time
        runs = problem.simulate_exact_many([full(x) for x in xs])
        return [np.concatenate(pos) - problem.observed for pos in runs]

    low, high = problem.theta_bounds()
    with np.errstate(over="ignore"):  # a runaway loop's columns: inf, a column that acts
        reference = np.linalg.norm(jac[:, idx] * (1 if rows is None else rows[:, None]), axis=0)
    done = polish(
        residuals,
        [problem.entries[i] for i in idx],
        theta[idx],
        iterations,
        reference=reference,
        bounds=(low[idx], high[idx]),
        slopes=np.ones(idx.size),  # internal units: the staircase's secant over +-STAIRCASE
        steps=_difference_step(problem),
        max_step=MAX_STEP,
        shortest=1 / 64,
        rows=rows,
    )
    theta = theta.copy()
    theta[idx] = done.x
    if done.jac is not None:
        jac[:, idx] = done.jac
    return theta, done.r, jac, done.iterations, done.converged


#: Forward-difference step of the exact polish, internal units (relative for the logs); and
#: where a controller reads the encoder's counts in the loop: there every value moves the
#: output in count flips, and a step of 1e-6 caught a few, each a jump of a count (a P 50 step
#: of the independent generator: the f_c column 0.295 m per unit at 1e-6, 0.120-0.137 at
#: 1e-4, 0.127-0.130 at 1e-3 and 1e-2; f_c's standard error 3.7e-5 where it lay 4e-4 off).
DIFFERENCE_STEP = 1e-6
COUNTS_DIFFERENCE_STEP = 1e-3


def _difference_step(problem) -> float:
    """The exact polish's forward-difference step for ``problem``'s recordings."""
    counts = any(s.counts_in_loop for s in problem.segments)
    return COUNTS_DIFFERENCE_STEP if counts else DIFFERENCE_STEP


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
    fitted, fixed) values {name: value} [SI] applied to every recording's plant (B_eq and f_c
    neither given here nor in a recording's [plant] start where the recordings put them, as
    a diagnosis's do); several recordings are weighed each against its own noise floor (the
    diagnosis's criterion, :class:`~tuning.estimation.engine.noise.RecordingNoise`); exact: also
    run the exact simulator before and after; progress: a line per stage on stderr; executor:
    what makes the exact runs several at a time (a :class:`jaxcart.workers.Helpers` the caller
    owns; default: one after the other in this process). Returns a :class:`FitResult`; a
    parameter the data do not determine is reported as not identifiable and held at its
    starting value. Runs in float64 whatever jax_enable_x64 says.
    Refused before any fitting (:func:`jaxcart.plausibility.check_fit_recordings`): a
    recording without motion, the same data twice, an open-loop input in other units.
    """
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
        theta, r, jac, n_it, ok = _levenberg_marquardt(problem, theta, active, width, cap, tol)
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
    segments = [fit_segment(rec, params, values0, settings) for rec in recordings]
    params = _expand(params, per_recording, segments)
    problem = _Problem(segments, params, settings, executor, given=values0)
    problem.start_where_read(_read_off(recordings, segments, params, values0))
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


def _read_off(recordings, segments, params, given) -> list:
    """The starts of the fitted B_eq and f_c read off the recordings, as a diagnosis starts
    (:func:`~tuning.estimation.engine.starts.read_off_each`), where neither the caller nor a
    recording's [plant] gives them. From the handout's B_eq, a joint fit of the real tap and
    PD run ended, with each recording weighed against its own floor, where the tap's start
    speed is 3.4 m/s (0.96 alone) and its position 51 mm off (0.21 mm), the PD run taking the
    cart."""
    named = set(given).union(*(r.plant_overrides for r in recordings))
    wanted = {"B_eq", "f_c"}.intersection(params) - named
    if not wanted:
        return []
    return starts.read_off_each(segments, recordings, [s.plant for s in segments], wanted)


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
        k = parameters.recording_of(name)
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
    if settings.lm_iterations == 0:  # FitSettings.exact_only: the start, its smooth Jacobian
        return _levenberg_marquardt(problem, theta, active, narrow, 0)[:3]
    first = len(run.stages)
    r = jac = None
    for k, width in enumerate(widths):
        # Gradient descent where the model is smoothest, to leave a poor start; from there
        # Levenberg-Marquardt converges in a few iterations at each narrower width.
        steps = settings.adam_steps if k == 0 else 0
        theta, r_adam = adam(problem, theta, active, width, steps, settings.learning_rate)
        if r_adam is not None:
            run.say(f"width {width:g} m/s: adam {steps} steps, RMS {_rms(r_adam) * 1e3:.4g} mm")
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
    direct = _levenberg_marquardt(problem, problem.theta0.copy(), active, narrow, cap)
    # Lower by more than 2 % of the (weighted) sum of squares, 1 % in RMS: where both find the
    # same minimum, the continuation's stays.
    d, c = problem.objective(direct[1])[0], problem.objective(r)[0]
    if not (
        math.isfinite(d) and (not math.isfinite(c) or c - d > 0.02 * problem.sum_of_squares(r))
    ):
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
        parts = problem.split(r)
        weights = None if problem.noise is None else problem.noise.weights(parts)
        cov = covariance(problem.segments, names, None, jac[:, idx], parts, weights=weights)
        hac, singular = cov.robust, cov.singular
        # Relative standard errors (for log-scaled parameters the log-space error is that).
        rel = np.sqrt(np.diag(hac)) * np.asarray(
            [
                1.0
                if i >= p or parameters.is_log(problem.params[i])
                else parameters.LINEAR_SCALE
                / max(abs(float(parameters.to_value(problem.params[i], theta[i]))), 1e-3)
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
        if not zero[worst]:
            # Where the data do not depend on it, it stays where the fit left it: its start
            # may act (a limit starts below the largest command) where the fitted one does not.
            theta[i] = problem.theta0[i]
        held_at = float(parameters.to_value(name, theta[i]))
        source = _held_source(problem, name, zero[worst])
        run.say(f"{name}: {notes[name]}; holding it at {held_at:.4g}, {source}")
        active[i] = False
        if zero[worst]:
            # Held where it was, a value the residual does not depend on leaves the fit of the
            # others as it is: only its column leaves the covariance (a refit here took 26 s
            # of the built-in recordings' 119 s joint fit, a ramp's drive limit, to end where
            # it began).
            continue
        if settings.lm_iterations:
            label = f"Levenberg-Marquardt without {name}"
            narrow = settings.widths[-1]
            theta, r, jac = run.lm(label, problem, theta, active, narrow, settings.lm_iterations)
        theta, r, jac = polish(theta, r, jac)
    return theta, r, jac, _widened(problem, r, cov)


def _held_source(problem, name, where_fitted) -> str:
    """Where a held parameter's value comes from, in words."""
    if not where_fitted:
        return problem.start_source(name)
    effect = plantspec.effect_of_param(base_name(name))
    limit = " (a limit the runs never reached)" if effect is not None and effect.limits else ""
    return f"where the fit left it: the data do not depend on it there{limit}"


def _widened(problem, r, cov: Covariance) -> tuple:
    """(``cov`` with its standard errors widened where the model misfits, the noise floor [m],
    why the model misfits or "")."""
    floor = floor_of(problem.segments)
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
            value = float(parameters.to_value(name, theta[i]))
            slope = parameters.value_slope(name, value)
            out[asked] = Estimate(
                asked,
                value,
                slope * float(se_internal[i]),
                stderr_naive=slope * float(se_naive[i]),
                edge=parameters.at_edge(name, value),
            )
        else:
            held = float(parameters.to_value(name, theta[i]))
            moved = not np.isclose(theta[i], problem.theta0[i])
            note = f"{notes[name]}; held at {held:.4g}, {_held_source(problem, name, moved)}"
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
        plant = seg.plant.replace(**smooth_runs.replacements(seg.plant, pv))
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
            per_run.setdefault(base_name(name), []).append(
                float(parameters.to_value(name, theta[i]))
            )
        else:
            values[name] = float(parameters.to_value(name, theta[i]))
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


def _why(name, j, idx, cov, singular, zero, problem, theta) -> str:
    """Why parameter ``name`` (entry j of idx) is not identifiable, in one line."""
    i = int(idx[j])
    p = len(problem.params)
    if parameters.is_log(name) and theta[i] < problem.theta0[i] - 8:  # shrunk 3000-fold: to zero
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
