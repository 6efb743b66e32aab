"""The independent generator's sampled loop: a true cart (:class:`TrueCart`, its own physics in
:mod:`tuning.verification.physics`) run through an experiment with the artefacts of a real
recording (:mod:`tuning.verification.artefacts`), and a tuned controller judged on a true cart.

    instant tau_k = k Ts + jitter_k:  y_k = q floor((y(tau_k) + phase) / q)   (the encoder)
        closed loop: (u_k, v_k) = PID(r_k, y_k)  (the lab's law, tuning.verification.controller)
        open loop: u_k = the experiment's command;  tap: no drive, a hand's push
    u_k reaches the amplifier at tau_k + delay and is held until u_{k+1} does

The file records t_k = k Ts (the controller's nominal clock), y_k, u_k and r_k. Positions are in
the encoder's frame (0 at the start, up to the count's phase), as a recording's are.

>>> from jaxcart import PID
>>> from tuning.verification import experiments as ex
>>> cart = TrueCart(B_eq=4.6, f_c=0.3)
>>> run = simulate(cart, ex.step(PID(kp=40.0, kd=3.0, v_limit=6.0), 0.2, horizon=0.3))
>>> run.position.shape, bool(run.diverged)
((301,), False)
"""

from __future__ import annotations

import math
import os
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from hw.gains import read_gains
from tuning.verification.artefacts import NONE, Artefacts, draw, drift, push_profile
from tuning.verification.controller import DiscretePID
from tuning.verification.experiments import Experiment, step
from tuning.verification.physics import SUBSTEPS, Cart
from tuning.verification.truth import TrueCart

#: A run whose |y| exceeds this [m], or is not finite, has diverged (it stops there).
DIVERGED = 1e3
#: Event times within this of a piece's end [s] count as at it (rounding of k Ts + delay).
_EPS = 1e-12
#: Settling band of the step metrics: 2 % of the step (docs/design.md, "Metrics").
SETTLING_BAND = 0.02


@dataclass(frozen=True, eq=False)
class Run:
    """One run of the independent generator.

    time: t_k = k Ts as the file records it [s]; instants: when each sample was taken [s];
    position: what the encoder reported [m]; true_position: the cart in the encoder's frame at
    each instant [m]; velocity [m/s]; command: u_k sent [V] (zeros for a tap); unlimited: v_k
    before the software limit [V]; reference: r_k [m] (closed loop, else None); truth: the cart
    of this run (its drive as drawn for it); artefacts; seed; experiment; push: a tap's
    (shape, length [s], peak force [N]), else None; diverged: the run stopped at |y| > DIVERGED
    (later samples nan).
    """

    time: np.ndarray
    instants: np.ndarray
    position: np.ndarray
    true_position: np.ndarray
    velocity: np.ndarray
    command: np.ndarray
    unlimited: np.ndarray
    reference: np.ndarray | None
    truth: TrueCart
    artefacts: Artefacts
    seed: object
    experiment: Experiment
    push: tuple | None
    diverged: bool

    @property
    def kind(self) -> str:
        return self.experiment.kind


def simulate(
    cart: TrueCart,
    experiment: Experiment,
    artefacts: Artefacts = NONE,
    *,
    seed=0,
    substeps: int = SUBSTEPS,
) -> Run:
    """Run ``experiment`` on ``cart`` with ``artefacts`` (default: none), the random draws
    (encoder phase, jitter, drift, this run's drive, a tap's push) from ``seed``; RK4 on
    ``substeps`` sub-steps a sample (:mod:`tuning.verification.physics`)."""
    ts, n = experiment.sample_time, experiment.n
    draws = draw(artefacts, seed, n, ts)
    truth = cart.replace(
        gamma_scale=cart.gamma_scale * draws.gain_factor,
        v_sat=cart.v_sat * draws.limit_factor,
        i_max=cart.i_max * draws.limit_factor,
    )
    push, breaks, push_info = None, (), None
    if experiment.kind == "tap":
        truth = truth.replace(motor_connected=False)
        shape, length = draws.push
        peak = _push_peak(truth, experiment, shape, length, substeps)
        start = experiment.rest

        def push(t):
            return peak * push_profile(shape, (t - start) / length)

        breaks, push_info = (start, start + length), (shape, length, peak)
    model = Cart(
        truth,
        sample_time=ts,
        lag=truth.lag + artefacts.lag,
        wander=drift(artefacts, draws.drift_phases),
        push=push,
        substeps=substeps,
    )
    rows = _loop(model, experiment, artefacts, draws, breaks)
    return Run(
        time=np.arange(n) * ts,
        instants=draws.instants,
        reference=experiment.signal.copy() if experiment.kind == "closed_loop" else None,
        truth=truth,
        artefacts=artefacts,
        seed=seed,
        experiment=experiment,
        push=push_info,
        **rows,
    )


def _loop(model: Cart, experiment: Experiment, artefacts: Artefacts, draws, breaks) -> dict:
    """The sampled loop: the recorded arrays and whether it diverged."""
    n, delay = experiment.n, model.truth.delay
    q, phase = artefacts.quantization, draws.phase
    law = DiscretePID(experiment.pid) if experiment.kind == "closed_loop" else None
    signal = experiment.signal.tolist()
    out = {k: np.full(n, np.nan) for k in ("position", "true_position", "velocity")}
    out.update(command=np.full(n, np.nan), unlimited=np.full(n, np.nan))
    state = (0.0, 0.0, model.amplifier_input(0.0, 0.0))  # at rest, the amplifier settled
    pending, held, t = deque(), 0.0, 0.0
    breaks = deque(b for b in breaks if b > 0)
    diverged = False
    for k, tk in enumerate(draws.instants.tolist()):
        state, held = _advance_to(model, state, t, tk, pending, held, breaks)
        t = tk
        y = state[0]
        if not abs(y) <= DIVERGED:
            diverged = True
            break
        exact = y + phase
        read = q * math.floor(exact / q) if q > 0 else exact
        out["position"][k], out["true_position"][k], out["velocity"][k] = read, exact, state[1]
        if law is not None:
            seen = read if artefacts.reads_counts else exact
            if k == 0:
                law.start(signal[0], seen)
            u, v = law.update(signal[k], seen)
        else:
            u = v = signal[k] if experiment.kind == "open_loop" else 0.0
        out["command"][k], out["unlimited"][k] = u, v
        pending.append((tk + delay, u))
    return {**out, "diverged": diverged}


def _advance_to(model, state, t, t_end, pending, held, breaks):
    """The state at t_end from t [s], the held command switching as ``pending`` commands
    arrive and sub-steps cut at ``breaks`` (a push's start and end); (state, held command)."""
    while True:
        while pending and pending[0][0] <= t + _EPS:
            held = pending.popleft()[1]
        while breaks and breaks[0] <= t + _EPS:
            breaks.popleft()
        if t >= t_end - _EPS:
            return state, held
        nxt = t_end
        if pending and pending[0][0] < nxt:
            nxt = pending[0][0]
        if breaks and breaks[0] < nxt:
            nxt = breaks[0]
        state = model.advance(state, t, nxt, held)
        t = nxt


def _push_peak(truth: TrueCart, experiment: Experiment, shape, length, substeps) -> float:
    """The push's peak force [N] that brings the cart from rest to the tap's speed at the end
    of the push (secant iterations on the push alone)."""
    mean = {"rectangle": 1.0, "half_sine": 2 / math.pi, "triangle": 0.5, "trapezoid": 0.75}[shape]

    def speed_at_end(peak):
        model = Cart(
            truth,
            sample_time=experiment.sample_time,
            push=lambda t: peak * push_profile(shape, t / length),
            substeps=substeps,
        )
        return model.advance((0.0, 0.0, 0.0), 0.0, length, 0.0)[1]

    target = experiment.speed
    d = 1 if target > 0 else -1
    friction = d * (truth.static(d) + truth.viscous(d) * abs(target) / 2)
    a = truth.m * target / (length * mean) + friction / mean
    b = 1.1 * a
    fa, fb = speed_at_end(a) - target, speed_at_end(b) - target
    for _ in range(6):
        if fb == fa or abs(fb) < 1e-6 * abs(target):
            break
        a, b = b, b - fb * (b - a) / (fb - fa)
        fa, fb = fb, speed_at_end(b) - target
    return b


class StepMetrics(NamedTuple):
    """Step-response metrics (docs/design.md "Metrics"): rise_time 10-90 % [s]; settling_time:
    the first sample after the last one outside 2 % of the step [s] (inf if the run ends
    outside); overshoot [%]; steady_state_error |r - y| at the end [m]; peak_command max |u_k|
    [V]."""

    rise_time: float
    settling_time: float
    overshoot: float
    steady_state_error: float
    peak_command: float

    def meets(self, settling_time: float = 1.0, overshoot: float = 5.0) -> bool:
        """The lab's design problem: settling below 1 s, overshoot below 5 %."""
        return self.settling_time < settling_time and self.overshoot < overshoot


def step_metrics(run: Run, *, band: float = SETTLING_BAND) -> StepMetrics:
    """Metrics of a closed-loop step run, from the position the encoder reported (with
    :data:`NONE` artefacts, the cart's exact position)."""
    if run.reference is None:
        raise ValueError("step metrics need a closed-loop run")
    if run.diverged:
        return StepMetrics(math.inf, math.inf, math.inf, math.inf, math.inf)
    t, y, r = run.time, run.position, run.reference
    size = r[-1] - y[0]
    if size == 0:
        raise ValueError("step metrics: the reference does not step")
    z = (y - y[0]) / size
    crossed = [np.flatnonzero(z >= level) for level in (0.1, 0.9)]
    rise = t[crossed[1][0]] - t[crossed[0][0]] if crossed[1].size else math.inf
    outside = np.flatnonzero(np.abs(y - r[-1]) > band * abs(size))
    if outside.size == 0:
        settling = 0.0
    elif outside[-1] == y.size - 1:
        settling = math.inf
    else:
        settling = t[outside[-1] + 1] - t[0]
    return StepMetrics(
        rise_time=float(rise),
        settling_time=float(settling),
        overshoot=float(max(0.0, (z.max() - 1.0) * 100.0)),
        steady_state_error=float(abs(r[-1] - y[-1])),
        peak_command=float(np.max(np.abs(run.command))),
    )


class ControllerRun(NamedTuple):
    """A controller on a true cart: its run and step metrics."""

    run: Run
    metrics: StepMetrics


def run_controller(
    cart: TrueCart,
    controller,
    *,
    amplitude: float = 0.5,
    horizon: float = 3.0,
    artefacts: Artefacts = NONE,
    seed=0,
    substeps: int = SUBSTEPS,
) -> ControllerRun:
    """Run a controller on a true cart: a closed-loop step of ``amplitude`` [m] for ``horizon``
    [s] (the lab's design problem by default: 0.5 m, 3 s) and its step metrics.

    controller: a :class:`jaxcart.PID` (any settings), or the path of a gains file
    (``hw.gains``, "jaxcart-gains").
    """
    if isinstance(controller, str | os.PathLike):
        controller = read_gains(controller)
    run = simulate(
        cart, step(controller, amplitude, horizon=horizon), artefacts, seed=seed, substeps=substeps
    )
    return ControllerRun(run, step_metrics(run))
