"""Which of the handout's experiments a raw recording is, from its content and its names.

A student's QUARC/Simulink scopes save positions, voltages and errors in .mat files without
saying which experiment ran. :func:`recognise` looks at the samples (and the file, variable,
label and block names) and returns a :class:`Guess`: the experiment, the settings it implies
(controller, reference or input) and every piece of evidence with its strength, so that the
user sees why. Where the evidence is weak it says so (:meth:`Guess.question`) instead of
guessing. The experiments (their names are the lab's slots, tuning/lab/inputs.py):

    tap      Part (i)    cart tapped by hand, motor unplugged: no voltage, one push, coasting
    p_step   Part (ii)   P control k = 50 V/m, 6 V limit, step 0.4 m
    ramp     Part (iii)  open-loop voltage ramp 0.1 V/s
    p_error  Part (iii)  P control k = 10 V/m, step 0.2 m (the steady-state error)
    pi       Part (iv)   PI control k = 10 V/m, k_i = 15 V/(m s), step 0.2 m
    pid      Part (v)    the designed PID, one step
    slider   Part (v)    the designed PID, the cart sent to several positions with the slider

Content features (each an :class:`Evidence`, weight 1 weak, 2 moderate, 3 strong):

- the controller identified from the recorded voltage v: least squares of v on the PID's
  terms over the samples below the software limit, v = kp e + ki int(e) + kd de/dt with
  e = r - y (the step r unknown: v = kp r + ki r t - kp y - ki int(y) - kd dy/dt); the fit's
  R^2 says how strong it is, the gains say which experiment; the derivative is tried through
  the handout's filter (tau = 0.01 s) and as a pure difference, and the better fit kept;
- an open-loop ramp: v linear in time (R^2), its slope;
- a 6 V limit block: v held at its largest magnitude for several samples;
- the motion: how many times the cart moves, when the first move starts (a step at t = 0, a
  tap after the cart rested), whether it coasts (deceleration proportional to speed, no
  drive) or speeds up to the end (a ramp's growing drive), where it comes to rest (the
  handout's step sizes);
- without a voltage, the error e (recorded, or r - y) as physics tells it: a step (e(0) = r)
  with the reference unchanged (no jump faster than the cart moves); integral action (the
  cart rests, then moves again toward e = 0: under P control a cart at rest stays at rest);
  P control's Coulomb dead band (the cart rests at a constant error |e| <= f_c/(k gamma) for
  longer than an integral would let it: k_i |e| T volts more than friction holds); an
  overshoot or none (P 10 is overdamped on the cart, P 50 and the PI are not); a top speed
  within what P 10 can drive the cart to (10 gamma |r| / B_emf).

Name features: "tap", "ramp", "p50", "p10", "pi", "pid", "slider", "err" (weak: every part's
model has an error block) and the handout's numbering ("2.1pos" is Part (ii), "part1.1" Part
(i)) in file, variable, label and block names.

The experiment with the highest total weight is the guess when it has at least 3 and leads
the next by at least 2; otherwise the guess is weak. Units: s, m, V.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field

import numpy as np

from hw.handout import APPENDIX, ENCODER_RESOLUTION


@dataclass(frozen=True)
class Spec:
    """One of the handout's experiments: part, what it is, its kind, the handout's settings
    (controller gains kp [V/m], ki [V/(m s)], kd [V s/m], v_limit [V]; step [m]; ramp [V/s])."""

    part: str
    what: str
    kind: str
    controller: dict | None = None
    step: float | None = None
    ramp: float | None = None


EXPERIMENTS = {
    "tap": Spec("i", "tap test, motor unplugged", "tap"),
    "p_step": Spec(
        "ii", "P control k = 50 V/m, step 0.4 m", "closed_loop", {"kp": 50.0, "v_limit": 6.0}, 0.4
    ),
    "ramp": Spec("iii", "open-loop voltage ramp 0.1 V/s", "open_loop", ramp=0.1),
    "p_error": Spec("iii", "P control k = 10 V/m, step 0.2 m", "closed_loop", {"kp": 10.0}, 0.2),
    "pi": Spec(
        "iv",
        "PI control k = 10 V/m, k_i = 15 V/(m s), step 0.2 m",
        "closed_loop",
        {"kp": 10.0, "ki": 15.0},
        0.2,
    ),  # fmt: skip
    "pid": Spec("v", "the designed PID, step", "closed_loop", None, 0.5),
    "slider": Spec("v", "the designed PID, slider moves", "closed_loop"),
}
#: The parts' numbers as the handout writes them ("2.1pos" is Part (ii)).
PART_EXPERIMENTS = {
    "1": ("tap",),
    "2": ("p_step",),
    "3": ("ramp", "p_error"),
    "4": ("pi",),
    "5": ("pid", "slider"),
}
_ROMAN = {"i": "1", "ii": "2", "iii": "3", "iv": "4", "v": "5"}
WEIGHTS = {1: "weak", 2: "moderate", 3: "strong"}
#: The guess needs this total weight and this lead over the next experiment.
CONFIDENT_SCORE, CONFIDENT_LEAD = 3, 2
#: A cart moves when its speed is above this [m/s] (an encoder count per 2 ms is 1.1 cm/s).
MOVING_SPEED = 0.02
#: The Coulomb friction a working IP02 cart can have [N], with a wide margin (the lab's real
#: cart: 0.44 N).
FRICTION_MIN, FRICTION_MAX = 0.1, 1.5
#: The handout cart's force per volt gamma [N/V] (jaxcart.params; hw/handout.py's appendix).
GAMMA = (
    APPENDIX["eta_g"] * APPENDIX["Kg"] * APPENDIX["eta_m"] * APPENDIX["Kt"]
    / (APPENDIX["Rm"] * APPENDIX["r_mp"])
)  # fmt: skip
#: The handout cart's back-EMF damping B_emf [kg/s] (jaxcart.params).
B_EMF = (
    APPENDIX["eta_g"] * APPENDIX["Kg"] ** 2 * APPENDIX["eta_m"] * APPENDIX["Kt"] * APPENDIX["Km"]
    / (APPENDIX["Rm"] * APPENDIX["r_mp"] ** 2)
)  # fmt: skip
#: Faster than this [m/s] the cart cannot move (6 V drive: about 1 m/s): a faster change of
#: the recorded error is the reference's.
JUMP_SPEED = 5.0
#: The derivative filters tried when the controller is identified [s]: the handout's 0.01 s
#: first, and a pure backward difference (the lab's Part (v) run used one).
FILTERS = (0.01, 0.0)


@dataclass(frozen=True)
class Evidence:
    """One feature: what was measured (text), the experiments it supports, its weight."""

    text: str
    supports: tuple[str, ...]
    weight: int

    def line(self) -> str:
        return f"{self.text} [{WEIGHTS[self.weight]}]"


@dataclass(frozen=True)
class Traces:
    """A raw recording's samples (numpy float64, at ``sample_time`` [s] apart): position y [m],
    voltage v [V], error e = r - y [m], reference r [m], each or None; ``names``: the file,
    variable, label and block names it came with."""

    sample_time: float
    position: np.ndarray | None = None
    command: np.ndarray | None = None
    error: np.ndarray | None = None
    reference: np.ndarray | None = None
    names: tuple[str, ...] = ()


@dataclass
class Guess:
    """The experiment a recording is (None when no experiment has evidence), the evidence,
    whether it is ``confident``, and the settings the evidence gives: ``controller`` {kp, ki,
    kd, v_limit}, ``step`` [m], ``ramp`` [V/s] (None when not measured)."""

    experiment: str | None
    evidence: list[Evidence]
    scores: dict[str, int]
    confident: bool
    controller: dict | None = None
    step: float | None = None
    ramp: float | None = None
    notes: list[str] = field(default_factory=list)
    named: bool = False

    def title(self) -> str:
        if self.experiment is None:
            return "no experiment recognised"
        spec = EXPERIMENTS[self.experiment]
        strength = "strong evidence" if self.confident else "weak evidence"
        if self.named:
            strength = "named by the user"
        return f"Part ({spec.part}) {spec.what} [{self.experiment}] ({strength})"

    def lines(self) -> list[str]:
        """The guess and its evidence, one line each."""
        return (
            [self.title()]
            + [f"  - {e.line()}" for e in self.evidence]
            + [f"  - {note}" for note in self.notes]
        )

    def candidates(self) -> list[str]:
        """The two experiments with the most evidence, best first."""
        return sorted(self.scores, key=self.scores.get, reverse=True)[:2]

    def question(self, name: str, how: str | None = None) -> str:
        """One line that asks the user to name the experiment of ``name``; ``how`` says where
        (default: an index lab.toml, ``[recordings] PART = "name"``)."""
        ranked = self.candidates()
        maybe = " or ".join(f"{k} (Part ({EXPERIMENTS[k].part}))" for k in ranked)
        why = f"it may be {maybe}" if ranked else "nothing in it looks like the handout's"
        first = ranked[0] if ranked else "p_step"
        how = how or f'in lab.toml beside it, e.g. [recordings] {first} = "{name}"'
        return (
            f"{name}: the evidence is weak ({why}); name its part {how} (parts: "
            f"{', '.join(EXPERIMENTS)})"
        )


def recognise(traces: Traces, experiment: str | None = None) -> Guess:
    """The :class:`Guess` for one recording (see the module docstring); ``experiment``, when
    the user named it, is taken as the answer (the evidence is still measured and shown)."""
    evidence: list[Evidence] = []
    settings: dict = {}
    ts = float(traces.sample_time)
    error = traces.error
    if error is None and traces.reference is not None and traces.position is not None:
        error = np.asarray(traces.reference, dtype=float) - np.asarray(traces.position)
    if traces.reference is not None:
        r = np.asarray(traces.reference, dtype=float)
        settings["steady_reference"] = float(np.ptp(r[1:])) <= 1e-9 * max(1.0, np.max(abs(r)))
    if traces.command is not None:
        evidence += _voltage_features(traces, ts, settings)
    elif error is not None:
        evidence += _error_features(error, ts, settings)
    if traces.position is not None:
        evidence += _motion_features(traces, ts, settings)
    evidence += _name_features(traces.names)
    scores: dict[str, int] = {}
    for e in evidence:
        for name in e.supports:
            scores[name] = scores.get(name, 0) + e.weight
    ranked = sorted(scores.items(), key=lambda kv: kv[1], reverse=True)
    best = ranked[0][0] if ranked else None
    lead = ranked[0][1] - (ranked[1][1] if len(ranked) > 1 else 0) if ranked else 0
    confident = best is not None and scores[best] >= CONFIDENT_SCORE and lead >= CONFIDENT_LEAD
    if experiment is not None:
        if experiment not in EXPERIMENTS:
            raise ValueError(f"{experiment!r}: the experiments are {', '.join(EXPERIMENTS)}")
        best, confident = experiment, True
    guess = Guess(best, evidence, scores, confident, named=experiment is not None)
    if best is not None:
        _settings(guess, settings)
    return guess


# ---------------------------------------------------------------- the voltage


def _voltage_features(traces: Traces, ts: float, settings: dict) -> list[Evidence]:
    v = np.asarray(traces.command, dtype=float)
    out = []
    t = np.arange(v.size) * ts
    ramp = _line_fit(t, v)
    if ramp is not None and ramp[2] > 0.999 and ramp[1] > 0 and v[-1] - v[0] > 0.05:
        _, slope, r2 = ramp
        near = abs(slope - EXPERIMENTS["ramp"].ramp) < 0.3 * EXPERIMENTS["ramp"].ramp
        settings["ramp"] = slope
        text = f"the voltage rises linearly with time, {slope:.4g} V/s (R^2 = {r2:.5f})"
        out.append(Evidence(text + (": the handout's 0.1 V/s" if near else ""), ("ramp",), 3))
        return out
    limit = _limit(v)
    if limit is not None:
        settings["v_limit"] = limit[0]
        out.append(
            Evidence(
                f"the voltage is held at {limit[0]:.4g} V for {limit[1]} samples: a software "
                "limit block",
                ("p_step", "pid", "slider"),
                1,
            )
        )
    k0 = _rest_before(traces)
    ident = identify_controller(_from(traces, k0), ts, None if limit is None else limit[0])
    if ident is None:
        return out
    gains, r2, used, step = ident
    law = ", ".join(f"{k} = {gains[k]:.4g}" for k in ("kp", "ki", "kd"))
    text = f"the voltage is a PID of the position, {law} (R^2 = {r2:.4f} over {used} samples)"
    if k0:
        text += f" from its step at t = {k0 * ts:.3f} s"
        settings["late_step"] = k0 * ts
    weight = 3 if r2 > 0.99 else 2 if r2 > 0.95 else 0
    if weight == 0:
        moves = len(_moves(traces.position, ts)) if traces.position is not None else 0
        text = (
            f"the voltage is no PID of the position with a fixed reference (R^2 = {r2:.3f}); "
            f"the cart moves {moves} times"
        )
        out.append(Evidence(text, ("slider",), 2 if moves >= 2 else 1))
        return out
    settings.update(gains=gains, step=step, r2=r2)  # only what a fitting PID shows
    if step is not None:  # a PID of the position with one constant step r
        settings["steady_reference"] = True
    kp, ki, kd = gains["kp"], gains["ki"], gains["kd"]
    if kd > 0:
        out.append(Evidence(text + (": a PID" if ki else ": a PD"), ("pid", "slider"), weight))
    elif ki > 0:
        near = _near(kp, 10.0) and _near(ki, 15.0)
        out.append(Evidence(text + ": PI" + (", the handout's" if near else ""), ("pi",), weight))
    elif _near(kp, 50.0):
        out.append(Evidence(text + ": P with the handout's k = 50 V/m", ("p_step",), weight))
    elif _near(kp, 10.0):
        out.append(Evidence(text + ": P with the handout's k = 10 V/m", ("p_error",), weight))
    else:
        out.append(Evidence(text + ": P with a gain the handout does not use", ("p_step",), 1))
        out.append(Evidence("(Part (iii)'s P step uses another gain)", ("p_error",), 1))
    return out


#: The fewest samples at rest before a step that count as a scope started early (20 ms).
REST_BEFORE = 20


def _rest_before(traces: Traces) -> int:
    """The samples before a step where the scope started early: the command at 0 V and the
    cart at rest where it started (a PID with nothing to do), at least :data:`REST_BEFORE`;
    else 0. A controller is identified from the step on (the reference then starts there)."""
    if traces.command is None or traces.position is None:
        return 0
    v, y = np.asarray(traces.command, dtype=float), np.asarray(traces.position, dtype=float)
    moved = np.flatnonzero((np.abs(v) > 1e-3) | (y != y[0]))
    k0 = int(moved[0]) if moved.size else 0
    return k0 if REST_BEFORE <= k0 < v.size - REST_BEFORE else 0


def _from(traces: Traces, k0: int) -> Traces:
    """``traces`` from sample ``k0`` on."""
    if not k0:
        return traces
    cut = {f: getattr(traces, f) for f in ("position", "command", "error", "reference")}
    return dataclasses.replace(
        traces, **{f: None if a is None else np.asarray(a)[k0:] for f, a in cut.items()}
    )


def identify_controller(traces: Traces, ts: float, v_limit: float | None = None):
    """(gains {kp, ki, kd, tau}, R^2, samples used, step r [m] or None) of the PID that made
    the recorded voltage, by least squares over the samples below ``v_limit``; None when there
    are too few. The terms are e, int(e) and de/dt of the error e (recorded, or r - y), the
    derivative through each filter of ``FILTERS`` (tau [s]) and the best kept; with y alone
    the constant step r is estimated first (:func:`_steps_of`)."""
    v = np.asarray(traces.command, dtype=float)
    n = v.size
    free = np.ones(n, dtype=bool) if v_limit is None else np.abs(v) < v_limit * (1 - 1e-6)
    free[0] = False  # the derivative's kick at the step
    if free.sum() < 20:
        return None
    fits = [_identify(traces, v, free, ts, tau) for tau in FILTERS]
    fits = [f for f in fits if f is not None]
    if not fits:
        return None
    # The handout's filter unless another fits clearly better (a pure difference, the lab's
    # "PID" run): a P or PI has no derivative, and its fits tie.
    gains, r2, step = max(fits, key=lambda f: (f[1] > fits[0][1] + 1e-4, f is fits[0]))
    return gains, r2, int(free.sum()), step


def _identify(traces: Traces, v, free, ts: float, tau: float):
    """(gains, R^2, step or None) of :func:`identify_controller` for one filter ``tau``."""
    if traces.error is not None:
        e = np.asarray(traces.error, dtype=float)
        return (*_fit_pid(e, v, free, ts, tau=tau)[:2], None)
    if traces.position is None:
        return None
    y = np.asarray(traces.position, dtype=float)
    if traces.reference is not None:
        r = np.asarray(traces.reference, dtype=float)
        return (*_fit_pid(r - y, v, free, ts, tau=tau)[:2], None)
    steps = _steps_of(y, v, free, ts, tau)
    if not steps:
        return None
    # The step whose PID in e = r - y fits best (the simplest model's among near ties).
    spread = float(np.std(v[free])) or 1.0
    scored = [(r, _fit_pid(r - y, v, free, ts, select=False, tau=tau)[2]) for r in steps]
    floor = min(rms for _, rms in scored)
    r = next(r for r, rms in scored if rms <= 1.1 * floor + 1e-3 * spread)
    # r and ki trade off where the integral is small: a step within half a millimetre of
    # whole centimetres is taken as that (the handout's are 0.2, 0.4, 0.5 m).
    if abs(r - round(r, 2)) < 5e-4:
        r = round(r, 2)
    gains, r2, _ = _fit_pid(r - y, v, free, ts, tau=tau)
    return gains, r2, r


def _steps_of(y, v, free, ts: float, tau: float) -> list[float]:
    """Candidates for the constant reference r [m] of a PID that made v from y alone, one per
    model P, PD, PI, PID in y (v = c0 + c1 t - kp y - ki int(y) - kd dy/dt, c0 = kp r,
    c1 = ki r): r = c0 / kp. An intercept also takes up the integral's settled value, so the
    simplest model that fits is not always the right r: the caller tries each."""
    n = y.size
    columns = {
        "c0": np.ones(n),
        "kp": -y,
        "c1": np.arange(n) * ts,
        "ki": -np.cumsum(y) * ts,
        "kd": -_filtered_rate(y, ts, tau),
    }
    models = (("c0", "kp"), ("c0", "kp", "kd"), ("c0", "kp", "c1", "ki"), tuple(columns))
    steps = []
    for names in models:
        result = _least_squares({k: columns[k] for k in names}, v, free)
        if result is not None and abs(result[0]["kp"]) > 1e-9:
            steps.append(result[0]["c0"] / result[0]["kp"])
    return steps


def _fit_pid(e, v, free, ts: float, *, select: bool = True, tau: float = 0.01):
    """(gains, R^2, RMS residual [V]) of v = kp e + ki int(e) + kd de/dt on the samples
    ``free``; with ``select`` ki and kd are kept only where they lower the residual (by more
    than 10 % and 0.1 % of the voltage's spread): a P controller is not read as a PI with a
    tiny ki."""
    terms = {"kp": e, "ki": np.cumsum(e) * ts, "kd": _filtered_rate(e, ts, tau)}
    spread = float(np.std(v[free])) or 1.0

    def fit(names):
        result = _least_squares({k: terms[k] for k in names}, v, free)
        if result is None:
            return None
        coef, r2 = result
        resid = v[free] - sum(coef[k] * terms[k][free] for k in names)
        return coef, r2, float(np.sqrt(np.mean(resid**2)))

    names = ["kp", "ki", "kd"]
    full = fit(names)
    if full is None:
        return {"kp": 0.0, "ki": 0.0, "kd": 0.0, "tau": float(tau)}, 0.0, math.inf
    for term in ("kd", "ki") if select else ():
        reduced = fit([k for k in names if k != term])
        if reduced is not None and reduced[2] <= 1.1 * full[2] + 1e-3 * spread:
            names.remove(term)
            full = reduced
    coef, r2, rms = full
    gains = {k: float(coef.get(k, 0.0)) for k in ("kp", "ki", "kd")}
    return {**gains, "tau": float(tau)}, r2, rms


def _least_squares(columns: dict, target, mask):
    a = np.column_stack([np.asarray(c, dtype=float)[mask] for c in columns.values()])
    b = np.asarray(target, dtype=float)[mask]
    scale = np.linalg.norm(a, axis=0)
    if np.any(scale == 0):
        return None
    x, *_ = np.linalg.lstsq(a / scale, b, rcond=None)
    x = x / scale
    resid = b - a @ x
    total = float(np.sum((b - b.mean()) ** 2))
    r2 = 1.0 - float(np.sum(resid**2)) / total if total > 0 else 0.0
    return dict(zip(columns, map(float, x), strict=True)), r2


def _filtered_rate(x, ts: float, tau: float):
    """dx/dt through the first-order filter s / (tau s + 1), backward Euler [unit/s] (the
    control law's, hw/control_law.py; tau = 0: the backward difference)."""
    # lazy: scipy.signal costs 0.3-2.5 s at start-up (measured, 2 cores, idle to load 15; 0.6-0.8 s
    # by python -X importtime after jaxcart.plots): the parser imports this module, and only
    # this filter of the recognition needs it.
    from scipy.signal import lfilter

    a = tau / (tau + ts)
    rate = lfilter([1.0 / (tau + ts), -1.0 / (tau + ts)], [1.0, -a], x)
    rate[0] = 0.0
    return rate


def _line_fit(t, v):
    """(intercept, slope, R^2) of v against t, or None for a constant."""
    fit = _least_squares({"c0": np.ones_like(t), "c1": t}, v, np.ones(t.size, dtype=bool))
    if fit is None or np.ptp(v) == 0:
        return None
    coef, r2 = fit
    return coef["c0"], coef["c1"], r2


def _limit(v):
    """(limit [V], samples at it) when the voltage sits at its largest magnitude for at least
    5 samples (a limit block's flat top), else None; a limit within 1 % of 6 V is 6 V."""
    top = float(np.max(np.abs(v)))
    if top <= 0:
        return None
    held = int(np.sum(np.abs(np.abs(v) - top) <= 1e-9 * top))
    if held < 5:
        return None
    return (6.0 if _near(top, 6.0, 0.01) else top), held


def _near(x: float, target: float, tol: float = 0.05) -> bool:
    return abs(x - target) <= tol * abs(target)


# ---------------------------------------------------------------- the error and the motion


def _error_features(e, ts: float, settings: dict) -> list[Evidence]:
    """The step (e(0) = r), whether the reference stays put, and how the error settles."""
    e = np.asarray(e, dtype=float)
    r = float(e[0])
    if abs(r) < 1e-3:
        # Under a millimetre: no step of the handout's (a tail's last error, say).
        text = f"the recorded error starts at {r * 1e3:.3g} mm, under 1 mm: no step at t = 0"
        return [Evidence(text, (), 1)]
    # The cart cannot move faster than JUMP_SPEED: a faster change is the reference's.
    jumps = np.flatnonzero(np.abs(np.diff(e)) > max(1e-3, JUMP_SPEED * ts))
    if jumps.size:
        k = int(jumps[0])
        text = (
            f"the error jumps by {(e[k + 1] - e[k]) * 1e3:.3g} mm at t = {(k + 1) * ts:.3g} s, "
            "faster than the cart moves: the reference moved (slider moves?)"
        )
        return [Evidence(text, ("slider",), 2)]
    settings.update(step=r, steady_reference=True)
    out = []
    sizes = tuple(k for k, s in EXPERIMENTS.items() if s.step and _near(r, s.step))
    if sizes:
        which = " and ".join(EXPERIMENTS[k].what.split(",")[0] for k in sizes)
        text = f"the error steps to {r:.4g} m at t = 0: the handout's step for {which}"
        out.append(Evidence(text, sizes, 1))
    return out + _settling(e, ts)


def _settling(e, ts: float) -> list[Evidence]:
    """Integral action or P control's Coulomb dead band, from how the error ``e`` [m] of a
    step with a constant reference settles. Under P control (u = k e) a cart at rest sees a
    constant drive, below friction, and stays at rest: it stops inside the dead band
    |e| <= f_c / (k gamma) (tuning/lab/deadband.py) and never moves again. The integral of a
    PI grows while the cart sticks until it breaks away: the cart moves again toward e = 0."""
    q = ENCODER_RESOLUTION
    moves = _moves(e[0] - e, ts)  # the cart's travel
    if not moves:
        span = float(np.ptp(e))
        if span <= 2 * q:
            return [Evidence("the error does not change: the cart does not move", (), 1)]
        text = (
            f"the error changes by {span * 1e3:.3g} mm in no move of 2 mm faster than "
            f"{MOVING_SPEED * 1e3:g} mm/s: the cart creeps or rests"
        )
        return [Evidence(text, (), 1)]
    for (_, b0), (a1, b1) in zip(moves, moves[1:], strict=False):
        before, after = float(e[a1]), float(e[b1])
        if abs(before) > 3 * q and np.sign(after - before) == -np.sign(before):
            text = (
                f"the cart rests {(a1 - b0) * ts:.3g} s at e = {before * 1e3:.3g} mm, then "
                f"moves again toward e = 0 (to {after * 1e3:.3g} mm) with the reference "
                "unchanged: integral action (under P control a cart at rest stays at rest)"
            )
            return [Evidence(text, ("pi",), 3)]
    last = moves[-1][1]
    rest = (e.size - 1 - last) * ts
    if rest < 0.2:
        return []  # still moving at the end: nothing settled
    creep = _creeps_after_rest(e[last + 1 :], ts)
    if creep is not None:
        return [creep]
    final = float(np.mean(e[last + 1 :]))
    out = []
    # How far the cart went past the target or where it rests [m]: P 50 and the PI overshoot
    # (complex poles), P 10 does not (real poles, -2.7 and -5.8 1/s at B_eq = 1.5 kg/s, for
    # any B_eq above 0.9 kg/s).
    travel = np.sign(e[0]) * (e[0] - e)
    back = float(np.max(travel) - min(travel[-1], abs(e[0])))
    # Under P 10 the drive is at most 10 gamma |r| and the back-EMF alone damps the cart: it
    # moves no faster than that over B_emf (20 % margin for the cart's own gamma).
    k10, k50 = (EXPERIMENTS[k].controller["kp"] for k in ("p_error", "p_step"))
    fastest = float(np.max(np.abs(_speed(travel, ts))))
    p10 = fastest <= 1.2 * k10 * GAMMA * abs(e[0]) / B_EMF
    if back < 1e-3:
        text = (
            "the error falls to its rest without overshoot: an overdamped loop (P 10 on the "
            f"cart, or a PID tuned not to overshoot); the cart's top speed, {fastest:.2g} m/s,"
        )
        text += " is within" if p10 else " is more than"
        text += " what P 10 can drive it to"
        out.append(Evidence(text, ("p_error", "pid") if p10 else ("pid",), 2))
    if abs(final) <= 2 * q:
        text = "the error settles to zero (within 2 encoder counts): integral action, or P"
        return out + [Evidence(text + " control with little friction", ("pi",), 1)]
    text = f"the cart rests the last {rest:.3g} s at a constant error of {final * 1e3:.3g} mm"
    ki = EXPERIMENTS["pi"].controller["ki"]
    added = ki * abs(final) * rest  # [V], what the handout's integral adds meanwhile
    weight = 1
    if added * GAMMA > FRICTION_MAX:
        weight = 3
        text += (
            f": no integral action (k_i = {ki:g} V/(m s) would have added {added:.2g} V, "
            f"{added * GAMMA:.2g} N, more than any friction of the cart)"
        )
    # P 10 creeps to the band's edge: f_c = k gamma |e|; P 50 stops anywhere inside after
    # its overshoot: f_c >= k gamma |e|.
    f10, f50 = k10 * GAMMA * abs(final), k50 * GAMMA * abs(final)
    p10 = p10 and back < 1e-3 and FRICTION_MIN <= f10 <= FRICTION_MAX
    p50 = back >= 1e-3 and f50 <= FRICTION_MAX
    if p10:
        text += f"; P 10's Coulomb dead band, |e| = f_c/(k gamma) with f_c = {f10:.2g} N"
    elif p50:
        text += (
            f"; P 50's Coulomb dead band after its {back * 1e3:.3g} mm overshoot, |e| <= "
            f"f_c/(k gamma) with f_c >= {f50:.2g} N"
        )
    else:
        text += (
            f"; no P loop of the handout's holds it (k = 10 V/m would need f_c = {f10:.2g} N "
            f"and no overshoot, k = 50 V/m f_c >= {f50:.2g} N after one)"
        )
    held = ("p_error",) if p10 else ("p_step",) if p50 else ()
    return out + [Evidence(text, held, weight if held else 1)]


#: How far [m] a cart must creep on toward e = 0 after a rest of 0.2 s for integral action:
#: P 10's exponential approach to its band also pauses a count for 0.2 s and more, with
#: about q tau / 0.2 s left to go (tau its slow time constant: 4 counts, 0.09 mm, on the
#: built-in P 10 step); the real cart's PI crept 13 mm.
CREEP = 1e-3


def _creeps_after_rest(tail, ts: float) -> Evidence | None:
    """Integral action where, after the last move, the cart rests (the error constant for
    0.2 s or more) and then creeps on toward e = 0 by more than :data:`CREEP`, too slowly to
    count as a move (the real cart's PI step, lab1_4.1.mat: at rest at 19.2 mm for 0.7 s,
    then on to 6 mm at ~7 mm/s): under P control a cart at rest stays at rest."""
    q = ENCODER_RESOLUTION
    bounds = np.flatnonzero(np.diff(tail)) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [tail.size]])
    after = float(tail[-1])
    for a, b in zip(starts[:-1], ends[:-1], strict=True):  # the last stretch ends the run
        before = float(tail[a])
        if (b - a) * ts < 0.2 or abs(before) <= 3 * q or abs(after - before) <= CREEP:
            continue
        if np.sign(after - before) == -np.sign(before):
            text = (
                f"the cart rests {(b - a) * ts:.3g} s at e = {before * 1e3:.3g} mm, then creeps "
                f"on toward e = 0 (to {after * 1e3:.3g} mm) with the reference unchanged: "
                "integral action (under P control a cart at rest stays at rest)"
            )
            return Evidence(text, ("pi",), 3)
    return None


def _motion_features(traces: Traces, ts: float, settings: dict) -> list[Evidence]:
    y = np.asarray(traces.position, dtype=float)
    moves = _moves(y, ts)
    if not moves:
        return [Evidence("the cart does not move", (), 1)]
    out = []
    start = moves[0][0] * ts
    final = float(np.mean(y[-max(2, y.size // 20) :])) - float(y[0])
    if traces.command is None and traces.error is None:
        out.append(Evidence("no voltage recorded (the motor unplugged?)", ("tap",), 1))
    if len(moves) >= 3 and not settings.get("steady_reference"):
        where = np.unique(np.round([y[b] for _, b in moves], 2))
        out.append(
            Evidence(
                f"the cart moves {len(moves)} times and rests at {where.size} places",
                ("slider",),
                2,
            )
        )
        return out
    late = settings.get("late_step")
    if len(moves) == 1 and late is not None and late <= start <= late + 0.1:
        # The scope started early: the cart rests until its command steps, then moves once.
        steps = tuple(k for k, s in EXPERIMENTS.items() if s.step is not None)
        text = (
            f"the cart moves at t = {start:.3g} s, as its command steps, and comes to rest: one "
            "step, not slider moves"
        )
        out.append(Evidence(text, steps, 2))
    elif len(moves) == 1 and start > 0.1:
        out.append(
            Evidence(
                f"the cart rests {start:.3g} s, then moves once: not a step at t = 0",
                ("tap", "ramp"),
                1,
            )
        )
        coast = _coasting(y, ts, moves[0])
        driven = _speeding_up(y, ts, moves[0])
        if driven is not None:
            text = (
                f"from {start:.3g} s it moves faster and faster until the recording ends "
                f"({driven:.3g} s of it): driven by a growing voltage (a ramp), not a tap's coast"
            )
            out.append(Evidence(text, ("ramp",), 3))
        elif coast is not None:
            c, r2 = coast
            text = f"after the push it slows in proportion to its speed (c/M = {c:.3g} 1/s, "
            out.append(Evidence(text + f"R^2 = {r2:.3f}): coasting, no drive", ("tap",), 2))
    elif start <= 0.1 and traces.command is not None:
        steps = tuple(k for k, s in EXPERIMENTS.items() if s.step is not None)
        text = f"the cart moves at t = {start:.3g} s and comes to rest: one step, not slider moves"
        out.append(Evidence(text, steps, 2))
    elif start <= 0.1 and "step" not in settings:  # the recorded error gave the step
        near = [
            k
            for k, spec in EXPERIMENTS.items()
            if spec.step is not None and abs(final - spec.step) < 0.05 * spec.step
        ]
        text = f"the cart moves at t = {start:.3g} s and comes to rest {final:.4g} m away"
        if near:
            sizes = " or ".join(sorted({f"{EXPERIMENTS[k].step:g} m" for k in near}))
            out.append(Evidence(f"{text}: a step of the handout's {sizes}", tuple(near), 1))
        else:
            steps = tuple(k for k, s in EXPERIMENTS.items() if s.step is not None)
            out.append(Evidence(f"{text}: a step of a size the handout does not use", steps, 1))
        settings.setdefault("step_final", final)
    return out


def _speed(y, ts: float):
    """Speed [m/s] by central differences over 10 ms (encoder counts are 2.3e-5 m)."""
    w = max(1, int(round(0.005 / ts)))
    v = np.zeros_like(y)
    v[w:-w] = (y[2 * w :] - y[: -2 * w]) / (2 * w * ts)
    return v


def _moves(y, ts: float) -> list[tuple[int, int]]:
    """(first, last) sample of each move: speed above ``MOVING_SPEED``, pauses under 0.2 s
    joined, moves of under 2 mm dropped."""
    if y is None or y.size < 10:
        return []
    moving = np.abs(_speed(np.asarray(y, dtype=float), ts)) > MOVING_SPEED
    edges = np.flatnonzero(np.diff(np.concatenate([[0], moving.astype(int), [0]])))
    runs = list(zip(edges[::2], edges[1::2] - 1, strict=True))
    joined: list[list[int]] = []
    for a, b in runs:
        if joined and (a - joined[-1][1]) * ts < 0.2:
            joined[-1][1] = b
        else:
            joined.append([a, b])
    return [(a, b) for a, b in joined if abs(y[b] - y[a]) > 0.002]


def _speeding_up(y, ts: float, move) -> float | None:
    """How long [s] the cart has moved when the recording ends during ``move`` at its fastest
    (its speed, averaged over 0.1 s, highest in the last 0.1 s), when at least 0.5 s, else
    None: an open-loop ramp's growing drive; a tapped cart only slows down after the push."""
    a, b = move
    tail = int(round(0.1 / ts))
    if b < y.size - 1 - tail or (b - a) * ts < 0.5:
        return None  # at rest before the end, or too short to tell
    speed = np.abs(np.convolve(_speed(y, ts)[a:], np.ones(tail) / tail, mode="valid"))
    fastest = int(np.argmax(speed))
    return (b - a) * ts if fastest >= speed.size - tail else None


def _coasting(y, ts: float, move):
    """(c [1/s], R^2) of deceleration = -c speed after the fastest sample of a move (the
    speeds smoothed over 20 ms), or None when it does not fit."""
    w = max(1, int(round(0.02 / ts)))
    speed = np.convolve(_speed(y, ts), np.ones(w) / w, mode="same")
    a, b = move
    peak = a + int(np.argmax(np.abs(speed[a : b + 1])))
    seg = slice(peak + w, b)
    s = speed[seg]
    if s.size < 20:
        return None
    acc = np.gradient(s, ts)
    keep = np.abs(s) > 2 * MOVING_SPEED
    if keep.sum() < 20:
        return None
    fit = _least_squares({"c": -s[keep]}, acc[keep], np.ones(int(keep.sum()), dtype=bool))
    if fit is None:
        return None
    coef, _ = fit
    c = coef["c"]
    resid = acc[keep] + c * s[keep]
    r2 = 1.0 - float(np.sum(resid**2)) / float(np.sum(acc[keep] ** 2))
    if c <= 0 or r2 < 0.5:
        return None
    return c, r2


# ---------------------------------------------------------------- names


_WORDS = (  # (pattern, supports, what it says, weight)
    (r"tap|unplug|coast", ("tap",), "a tap", 2),
    (r"ramp", ("ramp",), "a ramp", 2),
    (r"(?<![a-z0-9])k?p_?50(?![0-9])|k_?50(?![0-9])", ("p_step",), "P 50", 2),
    (r"(?<![a-z0-9])k?p_?10(?![0-9])|k_?10(?![0-9])", ("p_error",), "P 10", 2),
    (r"(?<![a-z])pid(?![a-z])", ("pid", "slider"), "a PID", 2),
    (r"(?<![a-z])pi(?![a-z])", ("pi",), "PI", 2),
    (r"slider|slide", ("slider",), "slider moves", 2),
    # Weak: every part's model has an error block; the handout asks to save it in (iii), (iv).
    (r"(?<![a-z])err(or)?(?![a-z])", ("p_error", "pi"), "the error scope (Parts (iii), (iv))", 1),
)
# "part4", "part_iv", "part1.1" (strong: the user wrote the part) or "2.1pos" (the handout's
# numbering of the experiment steps, moderate).
_PART = re.compile(
    r"(?:part[ _-]?(?P<m>[1-5]|iii|ii|iv|v|i)(?![a-z0-9]))"
    r"|(?:(?<![a-z0-9])(?:lab|p)?[ _-]?(?P<n>[1-5])\.\d)"
)


def _name_features(names) -> list[Evidence]:
    out, seen = [], set()
    for raw in names:
        text = str(raw).lower()
        if not text:
            continue
        for pattern, supports, what, weight in _WORDS:
            if re.search(pattern, text) and (supports, text) not in seen:
                seen.add((supports, text))
                out.append(Evidence(f"the name {raw!r} says {what}", supports, weight))
        match = _PART.search(text)
        if match:
            number = match["n"] or _ROMAN.get(match["m"], match["m"])
            supports = PART_EXPERIMENTS[number]
            if (supports, text) not in seen:
                seen.add((supports, text))
                roman = [k for k, v in _ROMAN.items() if v == number][0]
                weight = 3 if match["m"] else 2
                out.append(Evidence(f"the name {raw!r} numbers Part ({roman})", supports, weight))
    return out


# ---------------------------------------------------------------- settings


def _settings(guess: Guess, found: dict) -> None:
    """The controller, step and ramp of the guessed experiment: the handout's where the
    measurement agrees with it (within 5 %), else the measurement, with a note for each."""
    spec = EXPERIMENTS[guess.experiment]
    if spec.kind == "open_loop":
        ramp = found.get("ramp", spec.ramp)
        guess.ramp = spec.ramp if _near(ramp, spec.ramp) else float(f"{ramp:.4g}")
        return
    if spec.kind != "closed_loop":
        return
    handout = dict(spec.controller or {})
    gains = found.get("gains")
    if gains is not None:
        controller = {}
        for key in ("kp", "ki", "kd"):
            value, book = gains[key], handout.get(key, 0.0)
            if book and _near(value, book):
                controller[key] = book
            else:
                controller[key] = float(f"{value:.4g}") if abs(value) > 1e-9 else 0.0
        if controller["kd"]:
            controller["tau"] = gains["tau"]
            how = f"the derivative filter that fits, tau = {gains['tau']:g} s"
        else:
            how = "no derivative"
        guess.notes.append(
            "controller: "
            + ", ".join(f"{k} = {controller[k]:g}" for k in ("kp", "ki", "kd"))
            + f" from the voltage ({how})"
        )
    elif handout:
        controller = {k: handout.get(k, 0.0) for k in ("kp", "ki", "kd")}
        guess.notes.append("controller: the handout's (no voltage recorded to measure it)")
    else:
        controller = None
        guess.notes.append("controller: unknown (no voltage recorded); add it to [controller]")
    if controller is not None:
        if "v_limit" in found:
            controller["v_limit"] = found["v_limit"]
        elif gains is None and "v_limit" in handout:
            controller["v_limit"] = handout["v_limit"]
    guess.controller = controller
    step = found.get("step")
    if step is None and "step_final" in found and spec.step is not None:
        step = spec.step if abs(found["step_final"] - spec.step) < 0.05 * spec.step else None
        if step is None:
            step = round(found["step_final"], 3)
            guess.notes.append(f"step: {step:g} m, where the cart came to rest (not measured)")
    if step is not None and math.isfinite(step):
        if spec.step is not None and abs(step - spec.step) < 0.002:
            step = spec.step
        else:
            step = round(step, 4)
        guess.step = step
