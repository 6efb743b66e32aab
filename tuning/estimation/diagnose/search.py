"""The diagnosis: a search over structures on the estimation engine, and its verdict.

    recordings --checks--> segments --round 1: every single structure, one batch--> scores
        --pairs, forward selection, backward step (batches)--> exact polish of the best
        --significance, ties, swapped corrections--> :class:`~.result.Diagnosis`

Each round fits its candidate structures in one batch (:class:`~tuning.estimation.engine.
batch.BatchFitter`), re-checks them on the exact simulator and scores them
(:func:`~.scoring.score`); the structure that leads is the best-scoring one whose every part is
physically there (:func:`~.significance.significance`), or a better-scoring one without its
idle parts (:meth:`Search.reduced`), and each of its parts is kept by held-out prediction
(:meth:`Search.select`). The structures live in :mod:`.structures`, their exact runs and polish
in :mod:`.candidate_runs`, their scores in :mod:`.scoring`; which parts are named
(significance, implausible values) in :mod:`.significance`; each run's own drive limits in
:mod:`.per_run`; the verdict on the finished search in :mod:`.verdict`.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time as _time

import jax
import numpy as np

from jaxcart.effects import REGISTRY
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.plantspec import handout_plant
from jaxcart.plausibility import check_distinct
from tuning.distributed import spread
from tuning.estimation.diagnose import (
    candidate_runs,
    crossval,
    friction_curve,
    locate,
    per_run,
    scoring,
    significance,
    structures,
    verdict,
)
from tuning.estimation.diagnose import controller as ctl
from tuning.estimation.diagnose.policy import (
    DIRECT_WIDTHS,
    ITERATIONS,
    K_MAX,
    LATER_WIDTHS,
    MIN_COASTING,
    MIN_COUNTS,
    MIN_SAMPLES,
    NESTED,
    POLISH,
    REWEIGHT,
    REWEIGHTS,
    SCREEN,
    SEEDS,
    SPREAD,
    TIE,
    WIDTHS,
)
from tuning.estimation.diagnose.result import Diagnosis
from tuning.estimation.diagnose.structures import PARAM_ERRORS, PER_RUN
from tuning.estimation.engine import exact_runs, parameters
from tuning.estimation.engine.batch import BatchFitter
from tuning.estimation.engine.covariance import Covariance, covariance, determined
from tuning.estimation.engine.coverage import Coverage
from tuning.estimation.engine.noise import (
    FLOOR_FACTOR,
    RecordingNoise,
    encoder_count,
    floor_of,
    misfits,
)
from tuning.estimation.engine.segments import counts_in_loop, prepare, recording_name
from tuning.estimation.engine.starts import start_values


def diagnose(
    recordings,
    *,
    start=None,
    progress=True,
    pairs: bool = True,
    processes=None,
    executor=None,
    curve: bool = False,
) -> Diagnosis:
    """Diagnose one recording or several of one cart jointly.

    recordings: :class:`jaxcart.files.Recording` (or a list); start: a start plant (a plant
    file's :class:`jaxcart.Plant`; default the handout's); progress: True (print to stderr),
    False or a callable taking one line. Returns a :class:`Diagnosis`.

    Several driven runs of one cart share the mechanics; each may have its own drive limits
    (the structures with PER_RUN free v_sat, i_max per run).

    processes: a :class:`tuning.distributed.Exchange` of a jax.distributed run: the candidates'
    batch fits, exact re-checks and exact polishes are split over the processes and every
    result gathered on every one, which then all hold the same diagnosis (process 0 reports).
    Inside ``processes.carry()`` (as ``jaxcart diagnose`` calls it), an exception one process
    meets is raised on every process at its next exchange, none waiting for another.

    executor: what makes the exact runs several at a time (a :class:`jaxcart.workers.Helpers`
    the caller owns; default: one after the other in this process). curve: where no structure
    explains the recordings, read friction as a curve of the speed and of the position as
    the last candidate (:mod:`.friction_curve`: named only where it predicts the recordings
    held out better).
    Runs in float64 whatever jax_enable_x64 says, and leaves it as it was.
    """
    with jax.enable_x64(True):
        d = _diagnose(recordings, start, progress, pairs, processes, executor)
        if curve and d.status == "diagnosed" and not d.explained:
            found = friction_curve.discover(
                list(recordings) if isinstance(recordings, list | tuple) else [recordings],
                d,
                executor=executor,
                say=_progress_printer(progress),
            )
            d.curve_plant = found.pop("plant", None)
            d.friction_curve = found
        return d


def _diagnose(recordings, start, progress, pairs, processes, executor) -> Diagnosis:
    say = _progress_printer(progress)
    t_start = _time.perf_counter()
    if not isinstance(recordings, list | tuple):
        recordings = [recordings]
    check_distinct(recordings)  # the same data twice is no repeat of the experiment
    names = [recording_name(r) for r in recordings]
    messages, checks, controllers, read_counts = _checks(recordings, say)
    if messages:
        for m in messages:
            say(m)
        return Diagnosis(names, "not diagnosed", messages, checks, seconds=verdict.elapsed(t_start))
    search = Search(recordings, controllers, read_counts, start, say, processes, executor)
    search.run(pairs)
    d = verdict.diagnosis(search, names, checks, t_start)
    say(
        f"{d.verdict}; RMS {d.rms_before * 1e3:.4f} mm -> {d.rms_after * 1e3:.4f} mm "
        f"(encoder floor {d.floor * 1e3:.4f} mm), {d.seconds:.1f} s"
    )
    return d


def _checks(recordings, say):
    """(messages refusing the recordings, controller checks, controllers inferred, whether
    each controller read whole encoder counts)."""
    messages = []
    for rec in recordings:
        problem = _excitation(rec, encoder_count(np.asarray(rec.position, dtype=float)))
        if problem:
            messages.append(problem)
    checks, controllers, read_counts = [], [], []
    for rec in recordings:
        chk = ctl.check(rec)
        read_counts.append(bool(chk and chk["reads_counts"]))
        inferred = None
        if chk is not None:
            checks.append({k: v for k, v in chk.items() if k != "inferred"})
            say(chk["message"])
            inferred = chk["inferred"]
            if inferred is not None:
                keys = ("kp", "ki", "kd", "tau", "derivative_on", "v_limit")
                checks[-1]["inferred"] = {k: getattr(inferred, k) for k in keys}
        controllers.append(inferred)
    return messages, checks, controllers, read_counts


class Search:
    """One diagnosis's search: the segments, the batch fitter, the candidates tried."""

    def __init__(self, recordings, controllers, read_counts, start, say, processes, executor=None):
        self.recordings, self.say, self.processes = recordings, say, processes
        segments = [
            prepare(r, c, min_coasting=MIN_COASTING)
            for r, c in zip(recordings, controllers, strict=True)
        ]
        start_plant = start if start is not None else handout_plant()
        base_plants = []
        for rec in recordings:
            p = start_plant
            if rec.kind == "tap" and not rec.meta.get("tap", {}).get("motor_connected", False):
                p = dataclasses.replace(p, motor_connected=False)
            base_plants.append(rec.plant(p) if rec.plant_overrides else p)
        self.base_plants, self.segments = counts_in_loop(base_plants, segments, read_counts)
        segments = self.segments
        # What a correct model leaves: the encoder's q / sqrt(12), or the white noise of data
        # that are not whole counts (jaxcart fit's floor).
        self.floor = floor_of(segments)
        self.widen_above = FLOOR_FACTOR * self.floor  # above it the residual is model error
        # Each recording against its own floor: the criterion and the joint fits' weights.
        self.noise = RecordingNoise(segments, FLOOR_FACTOR)
        self.repeat = scoring.repeat_levels(segments)
        say(
            f"diagnose {', '.join(s.name for s in segments)}: "
            f"{sum(s.target.size for s in segments)} samples fitted"
        )
        # Several driven runs of one cart: each may have its own drive limits (PER_RUN).
        runs = tuple(i for i, s in enumerate(segments) if s.motor)
        self.runs = runs if len(runs) >= 2 else ()
        # A PER_RUN structure's extra slots in a batch: its drive limits, one per run each (the
        # gain per run is never batched: gain_per_run).
        per = structures.limit_params() if self.runs else ()
        self.extra = len(per) * max(0, len(self.runs) - 1)
        self.fitter = BatchFitter(
            segments, self.base_plants, per_recording=per, max_shared=K_MAX, noise=self.noise
        )
        self.layout = self.fitter.layout
        self.memo = exact_runs.ExactMemo(executor=executor)
        self.nuis = [n for n in self.layout.names if parameters.base_name(n) in parameters.NUISANCE]
        commands = [
            r.command if s.motor else None for r, s in zip(recordings, segments, strict=True)
        ]
        self.coverage = Coverage.of(segments, commands)
        self.round1 = structures.candidate_list(
            any(s.motor for s in segments), self.runs, self.coverage
        )
        self.starts_all = start_values(
            segments, recordings, self.base_plants, parameters.superset()
        )
        motor = [p for p, s in zip(self.base_plants, segments, strict=True) if s.motor]
        self.ref_plant = motor[0] if motor else self.base_plants[0]
        # A parameter correction is measured from the start plant's value.
        self.neutral = {n: float(self.ref_plant.get(n)) for p in PARAM_ERRORS.values() for n in p}
        self.cands = []
        self.polished_once = set()  # ids of the candidates an exact polish has improved

    # ------------------------------------------------------------ fitting and judging

    def exact(self, c, values):
        """(exact residuals per segment, commands) of ``c`` at ``values`` (memoized)."""
        return candidate_runs.exact_residuals(
            c, self.segments, self.base_plants, values, self.layout, self.memo
        )

    def prefetch(self, pairs):
        """Make the exact runs of the (candidate, values) ``pairs`` at once (several at a
        time), into the memo; a distributed run's processes make their own shares instead."""
        if self.processes is None:
            seg, plants, lay = self.segments, self.base_plants, self.layout
            self.memo.fill(
                [j for c, v in pairs for j in candidate_runs.exact_jobs(c, seg, plants, v, lay)]
            )

    def run_round(self, cands, starts, number):
        """Fit ``cands`` in one batch, re-check each on the exact simulator and score it."""
        say = self.say
        say(
            f"fitting {len(cands)} candidate structures in one batch: "
            + ", ".join(c.name for c in cands)
        )
        problems = [
            (tuple(c.free) + tuple(self.nuis), s, {}) for c, s in zip(cands, starts, strict=True)
        ]
        # Padded to round 1's size, or half of it where the round fits: two compiled shapes
        # (kept on disk), and a small round costs about half a full one.
        n_pad = max(len(self.round1), len(cands))
        if len(cands) <= (n_pad + 1) // 2:
            n_pad = (n_pad + 1) // 2
        problems = problems + [problems[0]] * (n_pad - len(problems))
        t_fit = _time.perf_counter()
        widths = WIDTHS if number == 1 else LATER_WIDTHS
        results = self.fitter.fit(
            problems,
            widths,
            ITERATIONS[-len(widths) :],
            kmax=K_MAX + self.extra + len(self.nuis),
            progress=lambda w, c: say(f"  width x{w:g}: smooth RMS {scoring.costs_text(c)}"),
            share=self.processes,
        )
        say(f"  batch fit: {_time.perf_counter() - t_fit:.1f} s")
        for c, (vals, cost, jac, _r) in zip(cands, results, strict=False):
            c.values, c.rms_smooth, c.jac, c.round = vals, math.sqrt(cost), jac, number
        self.prefetch([(c, c.values) for c in cands])
        rechecked = spread(self.processes, cands, lambda c: ({}, self.exact(c, c.values)[0]))
        for c, (_, res) in zip(cands, rechecked, strict=True):
            c.residuals = res
            c.rms_exact = scoring.rms(res)
            c.score = scoring.score(c, c.residuals, self.noise)
            say(
                f"  candidate {c.name:<24} smooth {c.rms_smooth * 1e3:8.4f} mm   exact "
                f"{c.rms_exact * 1e3:8.4f} mm   score {c.score:10.1f}"
            )

    def direct(self, cands, starts):
        """``cands`` fitted again straight from ``starts`` at the narrow DIRECT_WIDTHS, in one
        batch (the width is an argument of the compiled step: nothing compiles); a candidate
        keeps these values where they lower its exact residual."""
        problems = [
            (tuple(c.free) + tuple(self.nuis), s, {}) for c, s in zip(cands, starts, strict=True)
        ]
        results = self.fitter.fit(
            problems,
            DIRECT_WIDTHS,
            (ITERATIONS[-1],) * len(DIRECT_WIDTHS),
            kmax=K_MAX + self.extra + len(self.nuis),
            share=self.processes,
        )
        values = [vals for vals, _cost, _jac, _r in results]
        self.prefetch(list(zip(cands, values, strict=True)))
        rechecked = spread(
            self.processes,
            list(zip(cands, values, strict=True)),
            lambda cv: ({}, self.exact(*cv)[0]),
        )
        for c, vals, (_, res), (_, _, jac, _) in zip(
            cands, values, rechecked, results, strict=True
        ):
            if self.better(res, c):
                self.keep(c, vals, res, jac)

    def peaks(self, c) -> dict:
        """The largest command and armature current of ``c``'s own runs (motor segments): over
        all of them, and of each (``command@i``) for a limit free per run."""
        by_run = {}
        limits = {
            REGISTRY[e].limits
            for p in c.parts
            if p in structures.effect_params()
            for e in parameters.named_by(p)
        }
        if "command" in limits:
            _, cmds = self.exact(c, c.values)
            by_run["command"] = {
                i: float(np.nanmax(np.abs(u))) for i, u in enumerate(cmds) if u is not None
            }
        if "current" in limits:
            by_run["current"] = candidate_runs.current_peaks(
                c, self.segments, self.base_plants, c.values, self.layout
            )
        out = {}
        for k, each in by_run.items():
            out[k] = max(each.values(), default=0.0)
            out.update({f"{k}@{i}": v for i, v in each.items()})
        return out

    def cov_of(self, c) -> Covariance:
        """``c``'s parameter covariances at its values (free slots and nuisances)."""
        jac = c.jac / candidate_runs.fitter_scale(self.segments)
        names = list(c.free) + self.nuis
        weights = self.noise.weights(c.residuals)
        return covariance(
            self.segments, names, c.values, jac, c.residuals, self.widen_above, weights
        )

    def eligible(self, c) -> bool:
        """Every effect and correction of ``c`` significant
        (:func:`~.significance.significance`), at its current values (assessed once per set of
        values), and needed: a baseline within the misfit level already explains the recording,
        and nothing is named."""
        base = self.round1[0]
        key = (tuple(sorted(c.values.items())), base.rms_exact)
        if c.assessed != key:
            c.z, c.why, c.idle = {}, {}, ()
            if c.parts and not misfits(base.rms_exact, self.floor):
                c.why = {
                    p: f"not needed: the baseline explains the recording (RMS "
                    f"{base.rms_exact / self.floor:.1f} times the encoder floor)"
                    for p in c.parts
                }
            elif c.parts:
                stderr = self.cov_of(c).stderr
                sig = significance.significance(
                    c.parts, c.values, stderr, self.peaks(c), self.neutral
                )
                c.z = {k: v["z"] for k, v in sig.items()}
                c.why = {k: v["why"] for k, v in sig.items()}
                c.idle = _idle_parts(c.parts, sig)
            c.assessed = key
        return not c.why_not

    def choose(self, cs):
        """The structure that leads: by score, the first structure that is eligible (the
        baseline always is), or whose only ineligible parts are idle, without them
        (:meth:`reduced`)."""
        for c in sorted(cs, key=lambda c: c.score):
            sub = c if self.eligible(c) else self.reduced(c)
            if sub is not None:
                return sub
        return None

    def reduced(self, c):
        """``c`` without its idle parts, where those are all that keeps it from being named
        and what is left is eligible; else None. A part fitted to where it does nothing one
        would name (M within its margin of the start plant's, a delay of 0.1 ms) can still
        lower the misfit by absorbing what no candidate models (an amplifier's 0.1 ms lag, an
        encoder's phase), and it does so for every structure alike: the structure that fits
        best with it is the one the data favour. On the independent generator's Coulomb
        friction by direction, with M free Coulomb by direction fits to 0.016 mm and a dead
        band by direction to 0.017 mm; with M held, the dead band fitted better (0.026 mm
        against 0.032 mm) and was named."""
        if not c.idle:
            return None
        sub = c
        for part in c.idle:
            sub = self.without(sub, part)
        if not self.eligible(sub):
            return None
        self.say(f"  {'+'.join(c.idle)} of {c.name} does nothing one would name: {sub.name}")
        return sub

    @staticmethod
    def promising(cs, than):
        """The structures of ``cs`` that score better than ``than``, best first: the search
        goes on from these. Significance decides what is named, not where to search: a
        structure that is not named can lead the fits to the right basin (on the built-in
        P 50 step Coulomb + a spring with its rest point at the bound of its range does, and
        Coulomb alone reaches the floor from there), and standard errors widened for model
        error would stop the search on the recordings it matters most for."""
        return sorted((c for c in cs if c.score < than - 1.0), key=lambda c: c.score)

    def better(self, residuals, c) -> bool:
        """Whether ``residuals`` [m] (one array per recording) fit better than ``c``'s own: a
        lower misfit, each recording against its own level (what the fits minimise)."""
        return not c.residuals or self.noise.misfit(residuals) < self.noise.misfit(c.residuals)

    def polished(self, c, start, reach=None):
        """(values, [exact residuals per segment..., the Jacobian in the batch fit's form],
        converged); ``reach``: a score the re-fit is for (it stops early where it cannot come
        near). Each recording is weighed by its own misfit (iteratively reweighted: the
        weights at the start, then again at the values reached while they move by more than
        REWEIGHT, at most REWEIGHTS times: on the real tap, P 50 runs and PD run the tap goes
        0.63 -> 0.31 -> 0.23 -> 0.21 mm over successive weights)."""
        seg, plants, lay = self.segments, self.base_plants, self.layout
        target = None
        if reach is not None:
            target = SCREEN * scoring.cost_to_reach(c, reach, self.noise)
        weights = self.noise.weights(self.exact(c, start)[0])
        for _ in range(REWEIGHTS):
            values, jac, order, converged = candidate_runs.polish(
                c, seg, plants, start, lay, memo=self.memo, target=target, weights=weights
            )
            res = self.exact(c, values)[0]
            now = self.noise.weights(res)
            moved = np.max(np.abs(np.log(now / weights)))
            if jac is None or moved <= math.log(1 + REWEIGHT):
                break
            start, weights, target = values, now, None
        jac = candidate_runs.theta_jacobian(c, jac, order, values, self.nuis, seg)
        return values, [*res, jac], converged

    def polish_all(self, todo, reach=None):
        """Exact re-fits of (candidate, start) pairs, each kept only where it lowers the exact
        residual; independent, so split over the processes of a distributed run. ``reach``:
        see :meth:`polished`."""
        # A polish that converged at a candidate's values would only repeat itself.
        todo = [(c, start) for c, start in todo if c.settled != exact_runs.values_key(start)]

        def polish(item):  # (values, arrays) as spread gathers them: the flag an array too
            values, arrays, converged = self.polished(*item, reach)
            return values, [*arrays, np.array(float(converged))]

        done = spread(self.processes, todo, polish)
        for (c, _start), (values, arrays) in zip(todo, done, strict=True):
            self.keep(c, values, arrays[:-2], arrays[-2])
            settled = exact_runs.values_key(values)
            if bool(arrays[-1]) and exact_runs.values_key(c.values) == settled:
                c.settled = settled

    def keep(self, c, values, res, jac):
        if self.better(res, c):
            c.values, c.residuals, c.rms_exact = values, res, scoring.rms(res)
            c.score = scoring.score(c, c.residuals, self.noise)
            # The significance test's standard errors at these values: the exact re-fit's
            # Jacobian, not the smooth fit's at the values it started from; unless it leaves
            # a parameter undetermined that the smooth one determined (Coulomb under PI at
            # the truth: a step of f_c or B_eq moves where the cart sticks by a sample, and
            # both columns are that jump).
            p = len(c.free) + len(self.nuis)
            if jac.size and (
                c.jac is None or determined(jac[:, :p]) or not determined(c.jac[:, :p])
            ):
                c.jac = jac
            again = ", continued" if id(c) in self.polished_once else ""
            self.polished_once.add(id(c))
            self.say(
                f"  exact polish{again} {c.name:<20} exact {c.rms_exact * 1e3:8.4f} mm"
                f"   score {c.score:10.1f}"
            )

    def fit_round(self, grown, number, what):
        """Fit the (candidate, seed, addition) triples of one round and keep them."""
        t1 = _time.perf_counter()
        starts = structures.pair_starts(grown, self.starts_all, self.round1[0])
        self.run_round([c for c, _, _ in grown], starts, number)
        self.say(f"round {number} ({what}): {_time.perf_counter() - t1:.1f} s")
        self.cands += [c for c, _, _ in grown]
        return [c for c, _, _ in grown]

    # ------------------------------------------------------------ the search

    def run(self, pairs: bool):
        """Round 1, then (where nothing explains the recordings yet) pairs, forward selection
        and a backward step, then the exact polish of the most promising structures."""
        t0 = _time.perf_counter()
        starts1 = [
            {k: self.starts_all[parameters.base_name(k)] for k in c.free} for c in self.round1
        ]
        self.run_round(self.round1, starts1, 1)
        # A structure that ends worse than the baseline it nests has not fitted: its second
        # try starts from the baseline's fitted values, its own parameters at their starts.
        base = self.round1[0]
        self.direct(
            self.round1,
            [
                s if c.score <= base.score else {**s, **{k: base.values[k] for k in base.free}}
                for c, s in zip(self.round1, starts1, strict=True)
            ],
        )
        self.say(f"round 1 (compile + fit + exact checks): {_time.perf_counter() - t0:.1f} s")
        self.cands = list(self.round1)
        self.locate()
        # A single structure that already explains the data to the encoder's own error leaves
        # nothing for a pair to explain: round 2 is skipped (it costs a second batch).
        # The two best by score (a smooth fit may stall), and the best smooth fit: where the
        # smoothed stick-slip fits the recording but the exact re-check does not (stiction
        # under PI hunting: 0.048 mm smooth, 0.33 mm exact), the physics is found and only the
        # smoothing is off, which the exact polish mends.
        first = sorted(self.round1[1:], key=lambda c: c.score)[:2]
        first += [
            c for c in sorted(self.round1[1:], key=lambda c: c.rms_smooth)[:1] if c not in first
        ]
        self.polish_all([(c, dict(c.values)) for c in first])
        explained = min(c.rms_exact for c in self.round1) <= FLOOR_FACTOR * self.floor
        if explained:
            self.say("round 2 skipped: a single structure reaches the encoder floor")
        elif not misfits(base.rms_exact, self.floor):
            explained = True
            self.say("round 2 skipped: the baseline explains the recording")
        if pairs and not explained:
            seen, additions, level = self.pairs_round()
            number = self.forward(seen, additions, level)
            self.backward(seen, number)
        self.final_polish()
        self.gain_per_run()

    def locate(self):
        """Where the baseline's exact residual lies: windows and regressor tests."""
        base = self.round1[0]
        _, commands = self.exact(base, base.values)
        commands = list(commands)  # the memo's list is shared: replaced entries go in a copy
        for i, rec in enumerate(self.recordings):
            if rec.command is not None and self.segments[i].motor:
                commands[i] = np.asarray(rec.command, dtype=float)[self.segments[i].start :]
        self.commands = commands
        limits = [float(getattr(s.controller, "v_limit", math.inf)) for s in self.segments]
        self.wins = locate.windows(self.segments, base.residuals, commands, limits, self.floor)
        self.tests = locate.residual_tests(
            self.segments, base.residuals, commands, self.noise.total
        )

    def pairs_round(self):
        """Round 2: the singles that helped in pairs, each with the concealing friction, and
        (several runs of one cart) each drive limit free per run with it. Returns (structures
        seen, the additions of the forward selection, round 2's candidates)."""
        round1, base = self.round1, self.round1[0]
        friction = parameters.concealing_friction()
        good = self.promising(
            [c for c in round1[1:] if c.parts[0] in structures.effect_params()], base.score
        )
        by_name = {c.name: c for c in round1}
        # Each parameter correction that helped: the mass, and the drive's gain where a tap
        # beside a driven run tells the two apart (a gain 1.5 % off was left unnamed where only
        # the mass was paired: an independent simulator's PD step and tap, "not explained").
        # Without a tap they tie, the swap after the search names the plausible one, and both
        # paired would fill the batch with ties.
        motors = {s.motor for s in self.segments}
        corrections = [
            by_name[n] for n in PARAM_ERRORS if n in by_name and (n == "mass" or len(motors) == 2)
        ]
        fixes = self.promising(corrections, base.score) if corrections else []
        new = []
        top = good[:3]
        for i, a in enumerate(top):
            new += [(a, b) for b in top[i + 1 :]]
            if friction in by_name and not parameters.friction_family(a.name):
                new.append((a, by_name[friction]))
            new += [(a, c) for c in fixes]
        # The batch is padded to round 1's size anyway: the other effects fill it, each with
        # Coulomb friction where it helped (Coulomb conceals them: a delay, a current limit
        # under Coulomb friction help little or nothing alone), those that helped first.
        coulomb = by_name.get(friction)
        if coulomb is not None and self.runs:
            # Several runs of one cart: each drive limit free per run, under the friction
            # (with the limits shared the runs disagree, and friction alone fits neither).
            new = [(c, coulomb) for c in round1 if PER_RUN in c.parts] + new
        if coulomb is not None and self.promising([coulomb], base.score):
            helped = {id(c) for c in good}
            rest = good[3:] + [
                c
                for c in round1[1:]
                if c.parts[0] in structures.effect_params() and id(c) not in helped
            ]
            new += [(a, coulomb) for a in rest if not parameters.friction_family(a.name)]
        seen, round2 = set(), []
        for a, b in new:
            c = structures.pair(a, b)
            if set(c.parts) in seen or not structures.batchable(c.parts):
                continue
            seen.add(frozenset(c.parts))
            round2.append((c, a, b))
        round2 = round2[: len(round1)]
        level = self.fit_round(round2, 2, "pairs") if round2 else []
        # The forward selection extends by the singles that helped (Coulomb always among
        # them, as in the pairs: other effects conceal it).
        additions = good + list(fixes)
        if friction in by_name and all(a.name != friction for a in additions):
            additions.append(by_name[friction])
        additions.sort(key=lambda c: c.score)
        return {frozenset(c.parts) for c in self.cands}, additions, level

    def forward(self, seen, additions, level) -> int:
        """Forward selection: while the best structure of the last round is still above the
        misfit level and better than every structure before it, extend the best of that round
        by one more addition, as many free slots as one batch has. Returns the next round's
        number."""
        number, kmax = 3, K_MAX + self.extra
        while level:
            seeds = self.seeds(level)
            if not seeds:
                self.say(f"forward selection ends: round {number - 1} did not improve the score")
                break
            if not structures.extend(seeds, additions, set(seen), kmax=kmax):
                self.say(f"forward selection ends: no structure left within {kmax} slots")
                break
            # The lead polished on the exact simulator and the structures nested in it
            # re-fitted from its values (as after the search): a smooth fit stalled where the
            # exact cart sticks can hide that a simpler structure already explains it.
            lead = seeds[0]
            self.polish_all(
                [(lead, dict(lead.values))]
                + [
                    (c, {k: lead.values.get(k, c.values[k]) for k in c.values})
                    for c in self.cands
                    if c.parts and set(c.parts) < set(lead.parts)
                ]
            )
            if not misfits(min(c.rms_exact for c in self.cands), self.floor):
                self.say("forward selection ends: a structure explains the recording")
                break
            # Judged by the round's best structure, one whose drive limits are more than a
            # drive's spread included: it is not grown, but what it predicts is the round's.
            if number > 3 and not self.predicts_better(min(level, key=lambda c: c.score), level):
                break
            seeds = self.seeds(level)  # the polish may have improved earlier structures too
            grown = structures.extend(seeds, additions, seen, kmax=kmax) if seeds else []
            if not grown:
                break
            level = self.fit_round(grown, number, "forward selection")
            number += 1
        return number

    def predicts_better(self, lead, level) -> bool:
        """Whether the forward selection's ``lead`` predicts the recordings held out of its fit
        (:meth:`held_score`) better than the best structure before its round: a part that only
        lowers the in-sample residual is dropped by :meth:`select` anyway, and growing past it
        costs a round and a longer backward elimination (the real P 50 alone: saturation +
        Coulomb + a mass change fits better, predicts worse, and a fourth round is not fitted)."""
        this = {id(c) for c in level}
        before = min((c for c in self.cands if id(c) not in this), key=lambda c: c.score)
        if self.held_score(lead) < self.held_score(before):
            return True
        self.say(
            f"forward selection ends: {lead.name} predicts held out no better than "
            f"{before.name} ({self.held_score(lead):.1f} against {self.held_score(before):.1f})"
        )
        return False

    def seeds(self, level):
        """The structures of the last round that beat every structure before it, but those
        whose drive limits per run are not one drive's
        (:func:`~.per_run.per_run_inconsistency`): grown, they take the round's slots (the
        real tap, P 50 runs and PD run: a current limit per run at 0.69 A seeded two rounds,
        and saturation per run with Coulomb and the delay was never fitted); the final polish
        adds such a limit to the best structure instead (:meth:`_other_limits`)."""
        this = {id(c) for c in level}
        before = min(c.score for c in self.cands if id(c) not in this)
        sound = [
            c
            for c in level
            if not (PER_RUN in c.parts and per_run.per_run_inconsistency(c.values, self.peaks(c)))
        ]
        return self.promising(sound, before)[:SEEDS]

    def backward(self, seen, number):
        """Backward step: the best structure with a part that is not significant (a delay gone
        to 0 while M took over) tried without that part, from its values, in one batch."""
        lead = min(self.cands, key=lambda c: c.score)
        if len(lead.parts) < 3 or self.eligible(lead):
            return
        pruned = []
        for part in lead.parts:
            if any(lead.why.get(item) for item in significance.items(part)):
                c = structures.structure(tuple(x for x in lead.parts if x != part), lead.runs)
                if frozenset(c.parts) not in seen:
                    seen.add(frozenset(c.parts))
                    pruned.append((c, lead, lead))
        if pruned:
            self.fit_round(pruned, number, "without what is not significant")

    def final_polish(self):
        """The exact polish of the most promising structures, then every structure no richer
        than the best-scoring one, and those richer by one value that hold its effects,
        re-fitted from its values: a smooth fit that stalled in
        another basin (Coulomb friction creeps where the exact cart sticks) gets a fair exact
        re-fit, so that a simpler structure does not lose to a richer one and near-ties are
        found (Coulomb and deadzone on a P step). Of the forward selection's structures (three
        parts and more) only those nested in the best; of the others the NESTED best-scoring
        (each re-fit is a few dozen exact runs)."""
        base = self.round1[0]
        self.masks = scoring.window_masks(self.segments, self.wins)
        scoring.window_evidence(self.cands, base, self.masks)
        t2 = _time.perf_counter()
        ranked = [x for x in sorted(self.cands, key=lambda c: c.score) if x is not base]
        self.polish_all([(c, dict(c.values)) for c in ranked[:POLISH] + [base]])
        self.say(f"exact polish: {_time.perf_counter() - t2:.1f} s")
        done, previous = {id(base)}, None
        for _ in range(2):
            lead = min(self.cands, key=lambda c: c.score)
            if lead is previous:  # a second pass only from a new best-scoring structure
                break
            previous = lead
            nested = sorted(
                (
                    c
                    for c in self.cands
                    if id(c) not in done
                    and c is not lead
                    and c.parts
                    and len(c.free) <= len(lead.free)
                    and (len(c.parts) <= 2 or set(c.parts) < set(lead.parts))
                ),
                key=lambda c: c.score,
            )
            inside = [c for c in nested if set(c.parts) < set(lead.parts)]
            others = [c for c in nested if not set(c.parts) < set(lead.parts)][:NESTED]
            # A structure with the lead's effects and one value more that stands on them
            # (Stribeck beside the stiction it requires): from the lead's values, where its
            # smooth fit of a stick-slip may have stalled.
            richer = [
                c
                for c in self.cands
                if id(c) not in done
                and lead.effects
                and set(lead.effects) < set(c.effects)
                and len(c.free) == len(lead.free) + 1
                and all(
                    set(REGISTRY[e].requires) & set(lead.effects)
                    for e in set(c.effects) - set(lead.effects)
                )
            ]
            limits = self._other_limits(done)
            if not inside + others + richer + limits:
                break
            done.update(id(c) for c in inside + others + richer + [c for c, _ in limits])
            self.polish_all([(c, self._from(lead, c)) for c in inside])
            self.polish_all([(c, start) for c in richer for start in self._spread(lead, c)])
            self.polish_all(limits)
            # The others are re-fitted for near-ties: one that cannot come near the best
            # eligible score of the lead and the structures inside it stops early.
            eligible = [c.score for c in [lead, *inside] if self.eligible(c)]
            reach = min(eligible) + TIE if eligible else None
            self.polish_all([(c, self._from(lead, c)) for c in others], reach)

    def gain_per_run(self):
        """The best-scoring structure with the drive free per run (and no correction), again
        with the drive's gain free per run too, from its values and the start plant's gain,
        where nothing explains the recordings yet. A run's drive differs in its gain as in its
        limits, and a limit absorbs a gain it lacks: on the independent cart with a 12 ms lag
        and its own voltage limit each run (gains 1.0003 and 1.0057) a current limit of
        2.1 A was named in one run, which was left at 0.082 mm. Only here, from a structure
        the search reached: in its batches a run's gain and its voltage limit trade off where
        the run saturates, and on the real recordings a current limit per run with gains of
        0.92-1.06 then led the search astray (docs/diagnose.md). Named, as every part, where
        it predicts the recordings held out better (:meth:`select`)."""
        if not self.runs or not misfits(min(c.rms_exact for c in self.cands), self.floor):
            return
        bases = [c for c in self.cands if PER_RUN in c.parts and not c.corrections]
        if not bases:
            return
        base = min(bases, key=lambda c: c.score)
        c = structures.structure((*[p for p in base.parts if p != PER_RUN], "gain", PER_RUN),
                                 base.runs)  # fmt: skip
        if any(set(x.parts) == set(c.parts) for x in self.cands):
            return
        gain = PARAM_ERRORS["gain"][0]
        start = {**base.values, **{k: self.neutral[gain] for k in c.free if k not in base.values}}
        c.round = "gain per run"
        self.cands.append(c)
        self.polish_all([(c, start)])

    def _other_limits(self, done) -> list:
        """(structure, start) pairs: the best-scoring structure with the drive limits free per
        run but without one limit of the drive (of the POLISH best-scoring: a poor structure is
        not worth the exact runs), beside that limit free per run too, from its
        values and that limit's own from the best-scoring structure that fitted it per run.
        Within a batch's slots the forward selection grows one limit per run, and a structure
        whose limits spread more than one drive's does not seed it (the real PD run, held back
        early in its travel, draws a current limit of its own beside the voltage limit every
        driven run shows: 7.0 -> 2.0 mm, the others as they were, each recording predicted
        better held out)."""
        if not misfits(min(c.rms_exact for c in self.cands), self.floor):
            return []  # a structure explains the recordings already
        out, near = [], sorted(self.cands, key=lambda c: c.score)[:POLISH]
        for e in structures.effect_params():
            if not REGISTRY[e].limits:
                continue
            bases = [c for c in near if PER_RUN in c.parts and e not in c.parts]
            if not bases:
                continue
            base = min(bases, key=lambda c: c.score)
            parts = (*[p for p in base.parts if p != PER_RUN], e, PER_RUN)
            c = next((x for x in self.cands if set(x.parts) == set(parts)), None)
            c = c or structures.structure(parts, base.runs)
            own = [k for k in c.free if k not in base.values]
            donors = [x for x in self.cands if all(k in x.values for k in own)]
            if id(c) in done or not donors:
                continue
            donor = min(donors, key=lambda x: x.score)
            if all(x is not c for x in self.cands):
                c.round = base.round
                self.cands.append(c)
            out.append((c, {**base.values, **{k: donor.values[k] for k in own}}))
        return out

    def _spread(self, lead, c) -> list:
        """Starts of ``c`` from ``lead``'s values, its value ``lead`` lacks at each of
        SPREAD points over its plausible range (log-spaced for one fitted as a logarithm): a
        stick-slip fit is many-basined (Stribeck under PI hunting reaches 0.04 mm from 1 cm/s
        and stalls from 3 mm/s and 3 cm/s)."""
        extra = [n for n in c.free if n not in lead.values]
        starts = [self._from(lead, c)]
        for n in extra:
            lo, hi = parameters.bounds(n)
            grid = (
                np.geomspace(lo, hi, SPREAD + 2)
                if parameters.is_log(n)
                else np.linspace(lo, hi, SPREAD + 2)
            )
            starts += [{**self._from(lead, c), n: float(v)} for v in grid[1:-1]]
        return starts

    @staticmethod
    def _from(lead, c) -> dict:
        """``c``'s start for a re-fit from ``lead``'s values (its own where ``lead`` lacks one)."""
        return {k: lead.values.get(k, c.values[k]) for k in c.values}

    # ------------------------------------------------------------ selection by prediction

    def held_score(self, c) -> float:
        """``c``'s criterion on its held-out predictions (:func:`~.crossval.held_out`: each
        recording predicted by the cart fitted to the others, or each stretch of a single
        recording by the fit to the rest), the same criterion as the in-sample score
        (:func:`~.scoring.score`); computed once per set of values."""
        key = exact_runs.values_key(c.values)
        if c.held_out_key != key:
            residuals, values = crossval.held_out(self, c)
            c.held = {
                "residuals": residuals,
                "values": values,
                "score": scoring.score(c, residuals, self.noise),
            }
            c.held_out_key = key
        return c.held["score"]

    def without(self, c, part):
        """The structure of ``c`` without ``part``, fitted on the exact simulator from ``c``'s
        values (a structure the search has not made yet is made here)."""
        parts = structures.without_part(c.parts, part)
        made = structures.structure(parts, c.runs if PER_RUN in parts else ())
        sub = next((x for x in self.cands if set(x.parts) == set(parts)), None)
        start = self._start_from(c, sub or made)
        if sub is None:
            sub = made
            sub.name = sub.name or "baseline"
            sub.round = "selection"
            values, arrays, converged = self.polished(sub, start)
            sub.values, sub.residuals, sub.jac = values, arrays[:-1], arrays[-1]
            sub.rms_exact = scoring.rms(sub.residuals)
            sub.score = scoring.score(sub, sub.residuals, self.noise)
            if converged:
                sub.settled = exact_runs.values_key(values)
            self.cands.append(sub)
        else:
            self.polish_all([(sub, start)])
        return sub

    def _start_from(self, c, sub) -> dict:
        """Start values of ``sub`` from ``c``'s: a value ``c`` has; a shared drive limit at the
        median of ``c``'s values per run, one per run at ``c``'s shared one; else its own."""
        out = {}
        for n in list(sub.free) + self.nuis:
            kind = parameters.base_name(n)
            own = [v for k, v in c.values.items() if "@" in k and parameters.base_name(k) == kind]
            if n in c.values:
                out[n] = c.values[n]
            elif "@" not in n and own:
                out[n] = float(np.median(own))
            elif kind in c.values:
                out[n] = c.values[kind]
            else:
                out[n] = sub.values.get(n, self.starts_all[kind])
        return out

    def select(self, lead):
        """Backward elimination by prediction: from the structure that fits best, each part
        (an effect, a correction, the drive limits free per run) is dropped while the
        structure without it predicts the recordings held out of its fit at least as well
        (:meth:`held_score`, the penalties of the parts included): a part earns its place by
        what it predicts, not by what it fits."""
        current = lead
        while current.parts:
            here = self.held_score(current)
            subs = [self.without(current, p) for p in current.parts]
            subs = [s for s in subs if self.eligible(s)]
            self.say(
                f"  held out: {current.name} scores {here:.1f}; without "
                + ", ".join(
                    f"{'+'.join(p for p in current.parts if p not in s.parts)} "
                    f"{self.held_score(s):.1f}"
                    for s in subs
                )
            )
            if not subs:
                break
            sub = min(subs, key=self.held_score)
            if self.held_score(sub) > here:
                break
            dropped = "+".join(p for p in current.parts if p not in sub.parts)
            self.say(f"  {dropped} not named: it does not improve the held-out prediction")
            self.unearned.append(
                {"structure": current.name, "part": dropped, "with": here,
                 "without": self.held_score(sub)}
            )  # fmt: skip
            current = sub
        return current


def _idle_parts(parts, sig) -> tuple:
    """The parts all of whose items are idle (:func:`~.significance.significance`), where
    every item not named belongs to one of them (else none: dropping them would not make the
    structure eligible)."""
    idle = tuple(
        p for p in parts
        if any(v["part"] == p for v in sig.values())
        and all(v["idle"] for v in sig.values() if v["part"] == p)
    )  # fmt: skip
    return idle if all(v["part"] in idle for v in sig.values() if v["why"]) else ()


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


def _progress_printer(progress):
    if progress is True:
        return lambda text: print(text, file=sys.stderr, flush=True)
    if callable(progress):
        return progress
    return lambda text: None
