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
  -> choice by an information criterion on the exact residual, floored at the encoder's
     own error, with a penalty per parameter and per added effect; near-ties named
  -> exact polish of the choice, robust standard errors
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time as _time
from dataclasses import dataclass, field

import numpy as np

from jaxcart.errors import UserError
from jaxcart.files import signal64
from tuning.diagnose.batch import SHARED, BatchFitter, Layout, Segment

#: Effects a candidate adds, and the parameters it frees (B_eq is always free).
EFFECT_PARAMS = {
    "saturation": ("v_sat",),
    "coulomb": ("f_c",),
    "stiction": ("f_c", "f_s"),
    "delay": ("delay",),
    "deadzone": ("deadzone",),
    "spring": ("k_s", "y_rest"),
    "current_limit": ("i_max",),
}
#: Registered effects that are not candidates, and why (a test holds every registered effect
#: to be one or the other, so a new effect cannot be forgotten here).
NOT_CANDIDATES = {
    "quantization": "the encoder's count, read from each recording",
    "track_friction": "a 5-vector that triples the batch's compile time; fit it with jaxcart fit",
    "backlash": "its two-body sub-step makes the batch's compile several times longer; fit it "
    "with jaxcart fit",
}
#: The effects each candidate names (stiction is static above a kinetic level).
EFFECT_NAMES = {"stiction": ("coulomb", "stiction")}
PARAM_ERRORS = {"mass": ("M",), "gain": ("gamma_scale",)}
#: Effects that act only with the motor connected.
MOTOR_ONLY = {"saturation", "delay", "deadzone", "current_limit", "mass", "gain"}
#: Information criterion: penalty per free parameter (times log n_eff) and per added effect.
PENALTY_PER_PARAM = 1.0
PENALTY_PER_EFFECT = 12.0
#: The encoder floor of the criterion: RMS below FLOOR_FACTOR * q / sqrt(12) explains nothing.
FLOOR_FACTOR = 1.5
#: Near-ties: another structure within this many criterion units of the best is named too.
TIE = 6.0
WIDTHS = (4.0, 1.0, 0.3, 0.1)
ITERATIONS = (8, 8, 8, 8)
MIN_SAMPLES = 200
#: Free slots of every candidate (B_eq + two effects' parameters), so one compile serves all.
K_MAX = 5
#: Structures polished on the exact simulator (the best by score after the smooth fits).
POLISH = 4
MIN_COUNTS = 20


@dataclass
class Candidate:
    name: str
    parts: tuple  # effect or parameter-error names
    free: tuple  # free parameter names (shared)
    values: dict = field(default_factory=dict)
    rms_smooth: float = math.nan
    rms_exact: float = math.nan
    score: float = math.nan
    window_evidence: float = math.nan
    residuals: list = field(default_factory=list)
    jac: object = None
    scale: float = 1.0

    @property
    def effects(self) -> tuple:
        out = []
        for p in self.parts:
            if p in EFFECT_PARAMS:
                out += list(EFFECT_NAMES.get(p, (p,)))
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
            "window_evidence": self.window_evidence,
            "values": {k: v for k, v in self.values.items() if "@" not in k},
        }


@dataclass
class Diagnosis:
    """What :func:`diagnose` found (see :meth:`to_json` for the fields)."""

    recordings: list
    status: str  # "diagnosed" | "not diagnosed"
    messages: list
    controller_checks: list
    left_out: list = field(default_factory=list)
    corrected_parameters: list = field(default_factory=list)
    equivalent: list = field(default_factory=list)
    rms_before: float = math.nan
    rms_after: float = math.nan
    floor: float = math.nan
    parameters: dict = field(default_factory=dict)
    baseline: dict = field(default_factory=dict)
    windows: list = field(default_factory=list)
    tests: dict = field(default_factory=dict)
    candidates: list = field(default_factory=list)
    chosen: str = ""
    plant: object = None
    plant_file: str | None = None
    seconds: float = math.nan
    traces: list = field(default_factory=list)  # per segment: time, measured, baseline, after

    @property
    def verdict(self) -> str:
        if self.status != "diagnosed":
            return "not diagnosed: " + "; ".join(self.messages)
        if self.left_out:
            text = "left out: " + ", ".join(self.left_out)
        elif self.corrected_parameters:
            text = (
                "corrected parameters ("
                + ", ".join(self.corrected_parameters)
                + "), nothing left out"
            )
        else:
            text = "nothing left out: the baseline explains the recording to the encoder floor"
        if self.equivalent:
            text += "; fits equally well: " + "; ".join(" + ".join(e) for e in self.equivalent)
        return text

    def to_json(self) -> dict:
        return {
            "recordings": self.recordings,
            "status": self.status,
            "verdict": self.verdict,
            "messages": self.messages,
            "controller_checks": self.controller_checks,
            "left_out": self.left_out,
            "corrected_parameters": self.corrected_parameters,
            "equivalent": self.equivalent,
            "chosen": self.chosen,
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
            "encoder_floor": self.floor,
            "parameters": self.parameters,
            "baseline": self.baseline,
            "windows": self.windows,
            "tests": self.tests,
            "candidates": [c.to_json() for c in self.candidates],
            "plant_file": self.plant_file,
            "seconds": self.seconds,
        }


# ---------------------------------------------------------------- preparing


def _name(rec) -> str:
    path = getattr(rec, "path", None)
    return str(getattr(path, "name", path) or "recording")


def _excitation(rec, q) -> str | None:
    y = np.asarray(rec.position, dtype=float)
    name = _name(rec)
    if y.size < MIN_SAMPLES:
        return (
            f"{name}: too short to say anything ({y.size} samples, "
            f"{y.size * rec.sample_time:.3f} s); record at least {MIN_SAMPLES} samples of motion"
        )
    if not np.all(np.isfinite(y)):
        return f"{name}: column y has non-finite values; remove those rows"
    counts = np.ptp(y) / (q or 2.275e-5)
    if counts < MIN_COUNTS:
        return (
            f"{name}: no excitation: the cart moves {np.ptp(y) * 1e3:.3f} mm "
            f"({counts:.0f} encoder counts) in the whole recording; nothing to diagnose"
        )
    return None


def prepare(rec, controller=None) -> Segment:
    from tuning.fit import _initial_state, coasting_segment, encoder_count

    raw = np.asarray(rec.position, dtype=float)
    q = encoder_count(raw)
    y = raw + q / 2
    ts = float(rec.sample_time)
    time = np.asarray(rec.time, dtype=float)
    exp = rec.experiment
    if rec.kind == "tap":
        try:
            start, stop = coasting_segment(raw, ts, quantization=q or 2.275e-5)
        except ValueError as exc:
            raise UserError(f"{_name(rec)}: {exc}") from None
        if stop - start < 50:
            raise UserError(f"{_name(rec)}: the coasting part is under 50 samples; tap longer")
        y0, yd0 = _initial_state(time, y, start)
    else:
        start, stop = 0, raw.size
        y0, yd0 = float(y[0]), float(exp.yd0)
    import jax.numpy as jnp

    signal = jnp.asarray(signal64(rec)[start:stop])
    experiment = dataclasses.replace(exp, signal=signal, y0=y0, yd0=yd0)
    if controller is None:
        controller = rec.controller
    if controller is None:
        from hw.control_law import PID

        controller = PID(sample_time=ts)
    return Segment(
        name=_name(rec),
        kind=rec.kind,
        experiment=experiment,
        controller=controller,
        target=y[start:stop],
        time=time[start:stop],
        start=start,
        quantization=q,
        motor=rec.kind != "tap",
    )


# ---------------------------------------------------------------- candidates


def candidate_list(motor: bool) -> list[Candidate]:
    out = [Candidate("baseline", (), ("B_eq",))]
    names = list(PARAM_ERRORS) + list(EFFECT_PARAMS)
    for n in names:
        if n in MOTOR_ONLY and not motor:
            continue
        params = PARAM_ERRORS.get(n) or EFFECT_PARAMS[n]
        out.append(Candidate(n, (n,), ("B_eq", *params)))
    return out


def pair(a: Candidate, b: Candidate) -> Candidate:
    parts = tuple(dict.fromkeys(a.parts + b.parts))
    free = tuple(dict.fromkeys(a.free + b.free))
    return Candidate("+".join(parts), parts, free)


def _start_values(segments, recs, base_plants, free):
    """Start values of free parameters, from the data where a default would not act."""
    u_max = 0.0
    for rec, seg in zip(recs, segments, strict=True):
        if rec.command is not None:
            u_max = max(u_max, float(np.max(np.abs(rec.command))))
        elif seg.motor:
            from jaxcart.exact import simulate_exact

            res = simulate_exact(base_plants[0], seg.controller, seg.experiment)
            u_max = max(u_max, float(np.nanmax(np.abs(res.command))))
    u_max = max(u_max, 0.5)
    ymean = float(np.mean(np.concatenate([s.target for s in segments])))
    motor = any(s.motor for s in segments)
    start = {
        "B_eq": 5.4 if motor else 2.0,
        "M": 0.94,
        "gamma_scale": 1.0,
        "v_sat": 0.7 * u_max,
        "f_c": 0.3,
        "f_s": 0.5,
        "delay": 0.003,
        "deadzone": 0.2,
        "k_s": 3.0,
        "y_rest": ymean,
        "i_max": 0.7 * u_max / 2.6,
    }
    return {k: start[k] for k in free}


# ---------------------------------------------------------------- exact re-check


def exact_plants(cand: Candidate, base_plants, values):
    from jaxcart.plantspec import with_values

    named = {"B_eq": values["B_eq"]}
    for p in cand.corrections:
        for n in PARAM_ERRORS[p]:
            named[n] = values[n]
    for p in cand.parts:
        for n in EFFECT_PARAMS.get(p, ()):
            named[n] = values[n]
    if "f_s" in named:
        named["f_s"] = max(named["f_s"], named.get("f_c", 0.0))
    return [with_values(p, named) for p in base_plants]


class ExactMemo:
    """The last ``size`` exact runs of one diagnosis, by candidate structure and values: the
    polish re-runs points it has run (a trial it accepted is the next iteration's start, the
    polished point is re-checked), about a quarter of a diagnosis's exact runs (measured on
    the built-in P 50 step: 247 runs, 189 distinct). Results are shared: read-only arrays."""

    def __init__(self, size: int = 64):
        self.size = size
        self.runs: dict = {}
        self.hits = 0

    def get(self, cand, values, compute):
        key = (
            tuple(cand.parts),
            tuple(cand.corrections),
            tuple(sorted((k, float(v)) for k, v in values.items())),
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


def exact_residuals(cand, segments, base_plants, values, layout, memo: ExactMemo | None = None):
    """Exact-simulator residuals [m] (and commands [V] of motor segments) of ``cand`` at
    ``values``, one array per segment; ``memo`` reuses a run made before."""
    if memo is not None:
        return memo.get(
            cand, values, lambda: exact_residuals(cand, segments, base_plants, values, layout)
        )
    from jaxcart.exact import simulate_exact

    plants = exact_plants(cand, base_plants, values)
    out, commands = [], []
    for i, (seg, plant) in enumerate(zip(segments, plants, strict=True)):
        exp = seg.experiment
        if i in layout.nuisance:
            exp = dataclasses.replace(
                exp, y0=values.get(f"y0@{i}", exp.y0), yd0=values.get(f"yd0@{i}", exp.yd0)
            )
        res = simulate_exact(plant, seg.controller, exp)
        pos = np.asarray(res.position, dtype=float)
        if not np.all(np.isfinite(pos)):
            pos = np.where(np.isfinite(pos), pos, 1.0)
        out.append(pos - seg.target)
        commands.append(np.asarray(res.command, dtype=float) if seg.motor else None)
    return out, commands


def _rms(parts) -> float:
    r = np.concatenate(parts)
    return float(np.sqrt(np.mean(r * r)))


def _n_eff(segments) -> float:
    total = 0.0
    for seg in segments:
        q = seg.quantization
        if q > 0:
            counts = np.round(seg.target / q)
            runs = 1 + int(np.count_nonzero(np.diff(counts)))
        else:
            runs = seg.target.size
        total += min(runs, seg.target.size / 3)
    return max(total, 10.0)


def score(cand, mse, floor2, n_eff) -> float:
    k = len(cand.free) - 1
    effects = len(cand.parts)
    fit = n_eff * math.log(max(mse, floor2) / floor2)
    return fit + k * PENALTY_PER_PARAM * math.log(n_eff) + effects * PENALTY_PER_EFFECT


# ---------------------------------------------------------------- exact polish + errors


def _polish(cand, segments, base_plants, values, layout, iterations=3, memo=None):
    """Gauss-Newton on the exact simulator with forward differences (a few parameters)."""

    def residual(at):
        return np.concatenate(exact_residuals(cand, segments, base_plants, at, layout, memo)[0])

    names = [n for n in values]
    for _ in range(iterations):
        r0 = residual(values)
        cost0 = float(r0 @ r0)
        cols = []
        for n in names:
            v = values[n]
            h = 1e-4 * abs(v) + (1e-7 if Layout.kind(n) in ("delay", "y0", "y_rest") else 1e-6)
            trial = dict(values, **{n: v + h})
            r1 = residual(trial)
            cols.append((r1 - r0) / h)
        jac = np.column_stack(cols)
        scale = np.linalg.norm(jac, axis=0)
        scale[scale == 0] = 1.0
        js = jac / scale
        step, *_ = np.linalg.lstsq(js, -r0, rcond=None)
        step = step / scale
        improved = False
        for frac in (1.0, 0.5, 0.25):
            trial = {n: values[n] + frac * s for n, s in zip(names, step, strict=True)}
            if any(
                Layout.kind(n) in ("B_eq", "M", "gamma_scale", "v_sat", "f_c", "f_s", "k_s")
                and trial[n] <= 0
                for n in names
            ):
                continue
            if "delay" in trial:
                trial["delay"] = min(max(trial["delay"], 0.0), 0.024)
            if "deadzone" in trial:
                trial["deadzone"] = max(trial["deadzone"], 0.0)
            r1 = residual(trial)
            if float(r1 @ r1) < cost0:
                values, improved = trial, True
                break
        if not improved:
            break
    return values


def standard_errors(segments, names, values, jac, residuals):
    """Robust (run-clustered sandwich, encoder floor) standard errors in natural units."""
    from tuning.diagnose.batch import LOG

    jac = np.asarray(jac, dtype=float)
    r = np.concatenate(residuals)
    p = len(names)
    jac = jac[:, :p]
    # d value / d theta (log parameters).
    dv = np.array([values[n] if Layout.kind(n) in LOG else 1.0 for n in names])
    b = jac.T @ jac
    try:
        b_inv = np.linalg.pinv(b, rcond=1e-12)
    except np.linalg.LinAlgError:
        return {n: math.nan for n in names}
    s = np.zeros((p, p))
    offset = 0
    for seg in segments:
        n = seg.target.size
        jj, rr = jac[offset : offset + n], r[offset : offset + n]
        offset += n
        q = seg.quantization
        if q > 0:
            counts = np.round(seg.target / q)
            starts = np.concatenate([[0], 1 + np.flatnonzero(np.diff(counts))])
        else:
            starts = np.arange(n)
        g = np.add.reduceat(jj * rr[:, None], starts, axis=0)
        cs = np.add.reduceat(jj, starts, axis=0)
        s_data = g.T @ g
        s_enc = (q * q / 12.0) * (cs.T @ cs)
        s += s_data if np.trace(s_data) >= np.trace(s_enc) else s_enc
    cov = b_inv @ s @ b_inv
    se = np.sqrt(np.maximum(np.diag(cov), 0.0)) * np.abs(dv)
    return {n: float(x) for n, x in zip(names, se, strict=True)}


# ---------------------------------------------------------------- the diagnosis


def _progress_printer(progress):
    if progress is True:
        return lambda text: print(text, file=sys.stderr, flush=True)
    if callable(progress):
        return progress
    return lambda text: None


def diagnose(
    recordings, *, start=None, progress=True, pairs: bool = True, processes=None
) -> Diagnosis:
    """Diagnose one recording or several of one cart jointly.

    recordings: :class:`jaxcart.files.Recording` (or a list); start: a start plant (a plant
    file's :class:`jaxcart.Plant`; default the handout's); progress: True (print to stderr),
    False or a callable taking one line. Returns a :class:`Diagnosis`.

    processes: a :class:`tuning.tunerun.Exchange` of a jax.distributed run: the candidates'
    batch fits, exact re-checks and exact polishes are split over the processes and every
    result gathered on every one, which then all hold the same diagnosis (process 0 reports).
    Inside ``processes.carry()`` (as ``jaxcart diagnose`` calls it), an exception one process
    meets is raised on every process at its next exchange, none waiting for another.
    """
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxcart.params import handout_plant
    from tuning.diagnose import controller as ctl
    from tuning.diagnose import locate

    say = _progress_printer(progress)
    t_start = _time.perf_counter()
    if not isinstance(recordings, list | tuple):
        recordings = [recordings]
    names = [_name(r) for r in recordings]
    from tuning.fit import encoder_count

    messages = []
    for rec in recordings:
        problem = _excitation(rec, encoder_count(np.asarray(rec.position, dtype=float)))
        if problem:
            messages.append(problem)
    checks, controllers = [], []
    for rec in recordings:
        chk = ctl.check(rec)
        if chk is not None:
            checks.append({k: v for k, v in chk.items() if k != "inferred"})
            say(chk["message"])
            if chk["inferred"] is not None:
                inf = chk["inferred"]
                checks[-1]["inferred"] = {
                    "kp": inf.kp,
                    "ki": inf.ki,
                    "kd": inf.kd,
                    "tau": inf.tau,
                    "derivative_on": inf.derivative_on,
                    "v_limit": inf.v_limit,
                }
                controllers.append(inf)
                continue
        controllers.append(None)
    if messages:
        for m in messages:
            say(m)
        return Diagnosis(names, "not diagnosed", messages, checks, seconds=_elapsed(t_start))
    segments = [prepare(r, c) for r, c in zip(recordings, controllers, strict=True)]
    start_plant = start if start is not None else handout_plant()
    base_plants = []
    for rec in recordings:
        p = start_plant
        if rec.kind == "tap" and not rec.meta.get("tap", {}).get("motor_connected", False):
            p = dataclasses.replace(p, motor_connected=False)
        base_plants.append(rec.plant(p) if rec.plant_overrides else p)
    motor = any(s.motor for s in segments)
    qs = [s.quantization for s in segments if s.quantization > 0]
    q = float(np.mean(qs)) if qs else 0.0
    floor = max(q / math.sqrt(12), 1e-7)
    floor2 = (FLOOR_FACTOR * floor) ** 2
    n_eff = _n_eff(segments)

    say(f"diagnose {', '.join(names)}: {sum(s.target.size for s in segments)} samples fitted")
    from jaxcart.cache import enable_persistent_cache

    enable_persistent_cache()  # compiled batches kept on disk: a second diagnosis starts warm
    t0 = _time.perf_counter()
    fitter = BatchFitter(segments, base_plants)
    layout = fitter.layout
    memo = ExactMemo()
    nuis = [n for n in layout.names if "@" in n]
    round1 = candidate_list(motor)
    starts_all = _start_values(segments, recordings, base_plants, SHARED)

    def run_round(cands, starts):
        say(
            f"fitting {len(cands)} candidate structures in one batch: "
            + ", ".join(c.name for c in cands)
        )
        problems = [
            (tuple(c.free) + tuple(nuis), s, {}) for c, s in zip(cands, starts, strict=True)
        ]
        n_pad = max(len(round1), len(cands))
        problems = problems + [problems[0]] * (n_pad - len(problems))
        t_fit = _time.perf_counter()
        results = fitter.fit(
            problems,
            WIDTHS,
            ITERATIONS,
            kmax=K_MAX + len(nuis),
            progress=lambda w, c: say(f"  width x{w:g}: smooth RMS {_fmt_list(c, fitter)}"),
            share=processes,
        )
        say(f"  batch fit: {_time.perf_counter() - t_fit:.1f} s")
        for c, (vals, cost, jac, _r) in zip(cands, results, strict=False):
            c.values = vals
            c.rms_smooth = math.sqrt(cost)
            c.jac = jac
        rechecked = _spread(
            processes,
            cands,
            lambda c: ({}, exact_residuals(c, segments, base_plants, c.values, layout, memo)[0]),
        )
        for c, (_, res) in zip(cands, rechecked, strict=True):
            c.residuals = res
            c.rms_exact = _rms(res)
            c.score = score(c, c.rms_exact**2, floor2, n_eff)
            say(
                f"  candidate {c.name:<24} smooth {c.rms_smooth * 1e3:8.4f} mm   exact "
                f"{c.rms_exact * 1e3:8.4f} mm   score {c.score:10.1f}"
            )

    starts1 = [{k: starts_all[k] for k in c.free} for c in round1]
    run_round(round1, starts1)
    say(f"round 1 (compile + fit + exact checks): {_time.perf_counter() - t0:.1f} s")
    base = round1[0]

    # Locate on the baseline's exact residual.
    _, commands = exact_residuals(base, segments, base_plants, base.values, layout, memo)
    commands = list(commands)  # the memo's list is shared: replaced entries go in a copy
    for i, rec in enumerate(recordings):
        if rec.command is not None and segments[i].motor:
            commands[i] = np.asarray(rec.command, dtype=float)[segments[i].start :]
    limits = [float(getattr(s.controller, "v_limit", math.inf)) for s in segments]
    wins = locate.windows(segments, base.residuals, commands, limits, floor)
    tests = locate.residual_tests(segments, base.residuals, commands, n_eff)

    cands = list(round1)

    def polished(c, start):
        values = _polish(c, segments, base_plants, start, layout, memo=memo)
        return values, exact_residuals(c, segments, base_plants, values, layout, memo)[0]

    # A single structure that already explains the data to the encoder's own error leaves
    # nothing for a pair to explain: round 2 is skipped (it costs a second batch).
    first = sorted(round1[1:], key=lambda c: c.score)[:2]  # a smooth fit may have stalled
    for c, (values, res) in zip(
        first, _spread(processes, first, lambda c: polished(c, dict(c.values))), strict=True
    ):
        if _rms(res) < c.rms_exact:
            c.values, c.residuals, c.rms_exact = values, res, _rms(res)
            c.score = score(c, c.rms_exact**2, floor2, n_eff)
    explained = min(c.rms_exact for c in round1) <= FLOOR_FACTOR * floor
    if explained:
        say("round 2 skipped: a single structure reaches the encoder floor")
    if pairs and not explained:
        good = [
            c
            for c in round1[1:]
            if c.parts and c.parts[0] in EFFECT_PARAMS and c.score < base.score - 1.0
        ]
        good.sort(key=lambda c: c.score)
        top = good[:3]
        by_name = {c.name: c for c in round1}
        new = []
        for i, a in enumerate(top):
            for b in top[i + 1 :]:
                new.append((a, b))
            if "coulomb" in by_name and a.name not in ("coulomb", "stiction"):
                new.append((a, by_name["coulomb"]))
            for pe in ("mass",):
                if pe in by_name and by_name[pe].score < base.score - 1.0:
                    new.append((a, by_name[pe]))
        seen, round2 = set(), []
        for a, b in new:
            c = pair(a, b)
            if set(c.parts) in seen or set(c.parts) == {"coulomb", "stiction"}:
                continue
            seen.add(frozenset(c.parts))
            round2.append((c, a, b))
        round2 = round2[: len(round1)]
        if round2:
            starts2 = []
            for c, a, b in round2:
                s = {k: starts_all[k] for k in c.free}
                s.update({k: v for k, v in b.values.items() if k in c.free})
                s.update({k: v for k, v in a.values.items() if k in c.free})
                starts2.append(s)
            t1 = _time.perf_counter()
            run_round([c for c, _, _ in round2], starts2)
            say(f"round 2 (pairs): {_time.perf_counter() - t1:.1f} s")
            cands += [c for c, _, _ in round2]

    # Window evidence: how much of the windows' residual energy each candidate removes.
    masks = _window_masks(segments, wins)
    _window_evidence(cands, base, masks)

    # Exact polish (Gauss-Newton on the exact simulator) of the most promising structures.
    t2 = _time.perf_counter()
    ranked = sorted(cands, key=lambda c: c.score)

    def polish_all(todo):
        # Keep the exact re-fit only where it lowers the exact residual. Each (candidate,
        # start) independent: split over the processes of a distributed run.
        done = _spread(processes, todo, lambda item: polished(*item))
        for (c, _start), (values, res) in zip(todo, done, strict=True):
            keep(c, values, res)

    def keep(c, values, res):
        if _rms(res) < c.rms_exact:
            c.values, c.residuals, c.rms_exact = values, res, _rms(res)
            c.score = score(c, c.rms_exact**2, floor2, n_eff)
            say(
                f"  exact polish {c.name:<20} exact {c.rms_exact * 1e3:8.4f} mm"
                f"   score {c.score:10.1f}"
            )

    polish_all(
        [(c, dict(c.values)) for c in [x for x in ranked if x is not base][:POLISH] + [base]]
    )
    say(f"exact polish: {_time.perf_counter() - t2:.1f} s")
    best = min(cands, key=lambda c: c.score)
    # Every structure no richer than the choice, re-fitted from the choice's shared values
    # (B_eq, the start states): a smooth fit that stalled in another basin (Coulomb friction
    # creeps where the exact cart sticks) gets a fair exact re-fit, so that a simpler structure
    # does not lose to a richer one and near-ties are found (Coulomb and deadzone on a P step).
    done = {id(base)}
    for _ in range(2):
        nested = [
            c
            for c in cands
            if id(c) not in done and c is not best and c.parts and len(c.free) <= len(best.free)
        ]
        if not nested:
            break
        for c in nested:
            done.add(id(c))
        polish_all([(c, {k: best.values.get(k, c.values[k]) for k in c.values}) for c in nested])
        best = min(cands, key=lambda c: c.score)
    _window_evidence(cands, base, masks)
    ties = [
        c
        for c in cands
        if c is not best
        and c.score <= best.score + TIE
        and best.parts
        and c.parts
        and len(c.parts) <= len(best.parts)
        and set(c.parts) != set(best.parts)
        and (set(c.effects) != set(best.effects) or not best.effects)
        and not (set(best.parts) < set(c.parts))
    ]
    free_names = list(best.free) + nuis
    se = standard_errors(
        segments, free_names, best.values, best.jac / fitter_scale(segments), best.residuals
    )
    from jaxcart import plantspec

    params = {}
    for n in free_names:
        if "@" in n:
            continue
        params[n] = {
            "value": best.values[n],
            "stderr": se.get(n, math.nan),
            "unit": plantspec.unit(n),
        }
    base_se = standard_errors(
        segments,
        list(base.free) + nuis,
        base.values,
        base.jac / fitter_scale(segments),
        base.residuals,
    )
    baseline = {
        "B_eq": {
            "value": base.values["B_eq"],
            "stderr": base_se.get("B_eq", math.nan),
            "unit": "kg/s",
        },
        "rms": base.rms_exact,
    }
    plants = exact_plants(best, base_plants, best.values)
    motor_plants = [p for p, s in zip(plants, segments, strict=True) if s.motor]
    plant = motor_plants[0] if motor_plants else plants[0]
    traces = []
    base_res = base.residuals
    for seg, rb, ra in zip(segments, base_res, best.residuals, strict=True):
        traces.append(
            {
                "name": seg.name,
                "time": seg.time,
                "measured": seg.target,
                "baseline": seg.target + rb,
                "after": seg.target + ra,
            }
        )
    d = Diagnosis(
        names,
        "diagnosed",
        [],
        checks,
        left_out=list(best.effects),
        corrected_parameters=[PARAM_ERRORS[p][0] for p in best.corrections],
        equivalent=[list(c.effects) or [PARAM_ERRORS[p][0] for p in c.corrections] for c in ties],
        rms_before=base.rms_exact,
        rms_after=best.rms_exact,
        floor=floor,
        parameters=params,
        baseline=baseline,
        windows=wins,
        tests=tests,
        candidates=sorted(cands, key=lambda c: c.score),
        chosen=best.name,
        plant=plant,
        seconds=_elapsed(t_start),
        traces=traces,
    )
    say(
        f"{d.verdict}; RMS {d.rms_before * 1e3:.4f} mm -> {d.rms_after * 1e3:.4f} mm "
        f"(encoder floor {floor * 1e3:.4f} mm), {d.seconds:.1f} s"
    )
    return d


def _spread(processes, items, compute):
    """``[compute(item) for item in items]``, each a ({name: float}, [arrays]) pair; with
    ``processes`` (a :class:`tuning.tunerun.Exchange`) each item computed by one process and
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
