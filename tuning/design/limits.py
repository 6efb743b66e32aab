"""What limits the gains on a given cart: the tuner's search box derived from the cart rather
than fixed, and which of its limits sets a design.

- kp: the loop stays linear inside the settling band. At the band's edge (2 % of the step) the
  proportional action kp 0.02 |step| reaches the most voltage the drive gives at rest: the
  software limit, the amplifier's own (the fitted ``v_sat``: its mean over the runs) or, with a
  current-limited amplifier, Rm i_max (the armature current's limit at rest). A higher kp turns
  the last approach into a relay inside the band, which the encoder and the delay make chatter.
  So kp <= V / (0.02 |step|): 600 V/m for the lab's 6 V and 0.5 m.
- kd: the voltage ripple the encoder causes. One count q read within one sample moves the
  command by q (kp + kd/(tau + Ts)) (:func:`tuning.design.margins.ripple`); with at most
  :data:`RIPPLE` of it, kd <= (RIPPLE/q - kp_max) (tau + Ts), at the controller's tau (at the
  lowest tau of the box where tau is tuned too). The lab's tau = 0.01 s allows kd up to about
  90 V s/m; an unfiltered kd of 9 V s/m already makes 0.2 V.
- the rest (ki, tau, kb, v_limit) keep the tuner's box
  (:data:`tuning.design.problem.DEFAULT_BOUNDS`).

:func:`tuning.design.problem.tuning_problem` makes these the upper ends of kp and kd in every
tuner's box (``jaxcart tune``, the lab's pre-lab and its design for the cart), unless the user
bounds them; :attr:`tuning.design.result.TuneResult.binding` says which one sets a design.

>>> import jaxcart as jc
>>> box = gain_limits(jc.handout_plant(), jc.PID(v_limit=6.0), 0.5)
>>> round(box["kp"].bound), box["kp"].what
(600, 'the 6 V software limit')
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from jaxcart.metrics import SETTLING_BAND
from jaxcart.params import voltage_limit
from tuning.design.margins import encoder_count

#: The most voltage one encoder count may move the command by within a sample [V]: 1/30 of
#: the drive's 6 V (0.35 N of force toggling at up to 500 Hz: the motor whines and warms).
RIPPLE = 0.2
#: A gain within this share of its limit sits on it (tuning.design.result.on_bounds' rule).
ON_LIMIT = 0.01


@dataclass(frozen=True)
class Limit:
    """The upper limit of one gain on this cart: bound [its unit], what sets it (a few
    words) and why (a sentence with the numbers)."""

    name: str
    bound: float
    what: str
    why: str


def drive_voltage(plant, controller) -> tuple[float, str]:
    """(the most voltage the drive gives the cart at rest [V], what sets it): the smaller of
    the software limit and the amplifier's (:func:`jaxcart.params.voltage_limit`), and Rm
    i_max with a current-limited amplifier."""
    limit = float(voltage_limit(plant, controller))
    software = float(controller.v_limit)
    what = f"the {software:g} V software limit"
    if limit < software:
        what = f"the amplifier's {limit:.3g} V"
    if "i_max" in plant.param_names():
        at_rest = float(plant.Rm) * float(plant.get("i_max"))
        if at_rest < limit:
            limit = at_rest
            what = f"the current limit ({float(plant.get('i_max')):.3g} A: {at_rest:.3g} V at rest)"
    return limit, what


def gain_limits(plant, controller, step: float, *, tau_low: float | None = None) -> dict:
    """{"kp": Limit, "kd": Limit} on ``plant`` for ``controller``'s settings and a step of
    ``step`` [m] (module docstring); ``tau_low``: the lowest tau [s] of the box where tau is
    tuned too (kd's limit is then taken there), else None (the controller's tau)."""
    volts, what = drive_voltage(plant, controller)
    edge = SETTLING_BAND * abs(step)
    kp_max = volts / edge
    count = encoder_count(plant)
    tau = float(controller.tau) if tau_low is None else float(tau_low)
    h = tau + controller.sample_time
    kd_max = max(RIPPLE / count - kp_max, 0.0) * h
    return {
        "kp": Limit(
            "kp",
            kp_max,
            what,
            f"kp <= {volts:.3g} V / {edge * 1e3:.3g} mm = {kp_max:.4g} V/m: the loop stays "
            f"linear inside the settling band (2 % of the {abs(step):g} m step; beyond it the "
            "last approach is a relay that the encoder and the delay make chatter)",
        ),
        "kd": Limit(
            "kd",
            kd_max,
            "the encoder's ripple",
            f"kd <= ({RIPPLE:g} V / {count * 1e3:.4g} mm - kp) (tau + Ts) = {kd_max:.4g} V s/m "
            f"at tau = {tau:g} s: one encoder count moves the command by at most {RIPPLE:g} V",
        ),
    }


def binding(gains, limits: dict) -> list[Limit]:
    """The limits a design sits on (within :data:`ON_LIMIT` of the bound): what sets it. None
    of them: the cart's dynamics and the spec do."""
    out = []
    for name, limit in limits.items():
        value = float(getattr(gains, name))
        if math.isfinite(limit.bound) and value >= limit.bound * (1 - ON_LIMIT):
            out.append(limit)
    return out


def binding_text(gains, limits: dict) -> str:
    """One sentence: which derived limit sets the design, or that none does."""
    on = binding(gains, limits)
    if not on:
        return (
            "no limit of the cart binds: the gains sit inside their derived limits ("
            + "; ".join(f"{n} <= {lim.bound:.4g} by {lim.what}" for n, lim in limits.items())
            + "), set by the cart's dynamics and the spec"
        )
    return "the design is set by " + "; ".join(f"{lim.what}: {lim.why}" for lim in on)
