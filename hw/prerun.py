"""Plausibility of gains before the cart moves: the same loop on hw's simulated cart.

Two checks refuse gains (unless forced), each with its reason:
    unstable  a closed-loop pole outside the unit circle on the nominal (handout) cart: the
              linear loop of the discrete PID and the cart's exact zero-order-hold model,
              states (y, y', I, d, s_prev) of hw/control_law.py
    relay     the simulated run (the nominal cart with its 6 V amplifier and encoder counts,
              the run's own reference, virtual time) flips its command from one limit to the
              other more than ``RELAY_FLIPS_PER_S`` times a second: the loop chatters at the
              limit (a gain so high that one encoder count swings the full voltage)
and one warns: the simulated cart passing the track limit.

The simulated run is kept: ``jaxcart run`` / ``python -m hw run`` print the real run's metrics
beside it. Numpy only (hw never imports jaxcart).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hw.control_law import PID
from hw.devices.sim import CartParams, SimCart, _phis
from hw.loop import SIGNAL_REASONS, run_loop
from hw.safety import Limits

#: Full-swing flips of the command per second above which the loop is a relay.
RELAY_FLIPS_PER_S = 5.0
#: A command within this fraction of the limit is at the limit.
AT_LIMIT = 0.95
#: Poles this far outside the unit circle are unstable (an unused integrator sits on it).
UNIT_CIRCLE_TOL = 1e-6
#: The simulated run is at most this long [s] (the check takes ~10 ms per second).
MAX_SECONDS = 10.0
#: The relay check simulates at least this long [s], the last set point held.
MIN_SECONDS = 2.0


@dataclass(frozen=True)
class GainsCheck:
    """What the simulation of gains says before a run.

    poles: closed-loop poles on the nominal cart (complex); flips_per_s: full-swing command
    flips per second in the simulated run; at_limit: fraction of its samples at the limit;
    refusals: reasons to refuse the gains (one line each); warnings: the rest; simulated:
    the simulated run (a :class:`hw.loop.RunResult`)
    """

    poles: np.ndarray
    flips_per_s: float
    at_limit: float
    refusals: tuple
    warnings: tuple
    simulated: object


def closed_loop_matrix(pid: PID, params: CartParams | None = None) -> np.ndarray:
    """The linear closed loop x_{k+1} = A x_k of the PID and the cart (r = 0, no limits, no
    friction or delay), x = (y [m], y' [m/s], I [m s], d [m/s], s_prev [m])."""
    p = params or CartParams()
    ts, tau = float(pid.sample_time), float(pid.tau)
    e, p1, p2 = _phis(p.c / p.m, ts)
    bu = p.gamma / p.m  # acceleration per volt [m/s^2/V]
    dn = np.array([-1.0, 0.0, 0.0, tau, -1.0]) / (tau + ts)  # d_k from x (s_k = -y_k)
    u = np.array([-pid.kp, 0.0, pid.ki, 0.0, 0.0]) + pid.kd * dn
    return np.array(
        [
            np.array([1.0, p1, 0.0, 0.0, 0.0]) + p2 * bu * u,
            np.array([0.0, e, 0.0, 0.0, 0.0]) + p1 * bu * u,
            [-ts, 0.0, 1.0, 0.0, 0.0],
            dn,
            [-1.0, 0.0, 0.0, 0.0, 0.0],
        ]
    )


def simulate(pid: PID, reference, params: CartParams | None = None, *, padded: bool = False):
    """The run on the simulated cart, in virtual time, limits off (it shows what would
    happen), at most ``MAX_SECONDS`` long (``padded``: at least ``MIN_SECONDS``, the last
    set point held)."""
    r = np.asarray(reference, dtype=float)[: int(MAX_SECONDS / pid.sample_time) + 1]
    if padded:  # a short run still shows what the loop does once the cart arrives
        r = np.pad(r, (0, max(0, int(MIN_SECONDS / pid.sample_time) + 1 - r.size)), mode="edge")
    off = Limits(x_max=1e9, v_max=max(float(pid.v_limit), 1e-9), speed_max=1e9, jump_max=1e9)
    sim = run_loop(
        SimCart(params or CartParams()), pid, r, limits=off, clock="virtual", signals=False
    )
    if sim.fault is not None and sim.fault.startswith(SIGNAL_REASONS["SIGINT"]):
        raise KeyboardInterrupt  # Ctrl-C before the run: nothing was driven
    return sim


#: The lab's controller sample time [s] (1 kHz): the PID's default.
LAB_SAMPLE_TIME = PID().sample_time


def check_gains(pid: PID, reference, limits: Limits | None = None) -> GainsCheck:
    """Both checks of the module docstring on the nominal cart; see :class:`GainsCheck`."""
    limits = limits or Limits()
    poles = np.linalg.eigvals(closed_loop_matrix(pid))
    refusals, warnings = [], []
    worst = float(np.max(np.abs(poles)))
    gains = f"kp={pid.kp:g} ki={pid.ki:g} kd={pid.kd:g}"
    if worst > 1.0 + UNIT_CIRCLE_TOL:
        ts = float(pid.sample_time)
        slow = (
            f" at a sample time of {ts:g} s (the lab's loop runs at 0.001 s: sample_time in ms?)"
            if ts > LAB_SAMPLE_TIME * 20
            else ""
        )
        refusals.append(
            f"unstable: {gains} put a closed-loop pole at |z| = {worst:.6f} > 1 on the nominal "
            f"cart (the handout's){slow}; retune (jaxcart tune) or lower kp / ki"
        )
    sim = simulate(pid, reference, padded=True)
    u = sim.command
    lim = float(min(pid.v_limit, limits.v_max))
    at = np.abs(u) >= AT_LIMIT * lim
    flips = int(np.count_nonzero(at[1:] & at[:-1] & (u[1:] * u[:-1] < 0)))
    seconds = max(sim.n_samples - 1, 1) * pid.sample_time
    rate = flips / seconds
    share = float(np.mean(at)) if at.size else 0.0
    if rate > RELAY_FLIPS_PER_S:
        refusals.append(
            f"relay: with {gains} the simulated loop flips between +{lim:g} V and -{lim:g} V "
            f"{rate:.0f} times a second ({share * 100:.0f} % of the samples at the limit): one "
            "encoder count swings the full voltage; lower kp (and kd)"
        )
    reach = float(np.max(np.abs(sim.position))) if sim.n_samples else 0.0
    if reach > limits.x_max:
        warnings.append(
            f"the simulated cart reaches |y| = {reach:.3g} m, beyond the track limit "
            f"{limits.x_max:g} m: the run would stop there"
        )
    n = np.asarray(reference).size
    if sim.n_samples > n:  # the padded part was for the relay check only
        sim = simulate(pid, reference)
    return GainsCheck(poles, rate, share, tuple(refusals), tuple(warnings), sim)
