"""The tuning loss: smooth step metrics of the smoothed simulator, against the specification.

Gains are optimized in log space (theta = log gain), which keeps them positive and makes a step
of the optimizer a relative change (kp = 40 and kd = 5 move alike). For one gain set and one
plant, with the smooth surrogates Ts~ (settling time) and OS~ (overshoot) of
:mod:`jaxcart.surrogates`:

    loss = Ts~ / T_max + weight * ( relu(OS~ / OS_max - target) + relu(Ts~ / T_max - target)
                                     + E(target T_max) )

where E(t0) is the mean distance outside the settling band after t0, in band units
(:func:`jaxcart.surrogates.band_excess`): it keeps a gradient where the run never settles.

The hinge terms (an exact penalty: large slope, zero inside) dominate while the specification
is not met, so the optimizer first makes the gains feasible, then the first term drives the
settling time down toward the physical limit. ``target`` < 1 leaves a margin, because the smooth
model and the exact one differ slightly. Robust tuning takes a soft maximum of the loss over a
set of plants (softmax-weighted mean, :func:`jaxcart.surrogates.soft_max`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from jaxcart.errors import UserError
from jaxcart.metrics import SETTLING_BAND
from jaxcart.smooth import simulate
from jaxcart.smoothing import Smoothing
from jaxcart.surrogates import SmoothStepInfo, band_excess, smooth_step_info, soft_max

#: Gain order of every array of gains in tuning (as in jaxcart.batch): kp, kd, ki.
GAIN_NAMES = ("kp", "kd", "ki")


@dataclass(frozen=True)
class Spec:
    """The design problem (the lab's by default).

    step: reference step [m]; settling_time: bound on the 2 % settling time [s];
    overshoot: bound on the overshoot [%]; band: settling band [fraction of the step];
    horizon: simulated time [s], long enough that a slow integral creep shows (default the
        larger of 3 s and 3 x settling_time)
    """

    step: float = 0.5
    settling_time: float = 1.0
    overshoot: float = 5.0
    band: float = SETTLING_BAND
    horizon: float | None = None

    def __post_init__(self):
        if self.horizon is None and isinstance(self.settling_time, float | int):
            object.__setattr__(self, "horizon", max(3.0, 3.0 * float(self.settling_time)))
        for name in ("settling_time", "overshoot", "band", "horizon"):
            value = getattr(self, name)
            if not (isinstance(value, float | int) and value > 0):
                raise UserError(f"spec {name} = {value!r}: it must be a positive number")
        if not (isinstance(self.step, float | int) and self.step != 0):
            raise UserError(f"spec step = {self.step!r} m: it must be a nonzero number")
        if self.horizon <= self.settling_time:
            raise UserError(
                f"spec horizon = {self.horizon} s must exceed the settling bound "
                f"{self.settling_time} s (use about 3x)"
            )


@dataclass(frozen=True)
class LossSettings:
    """Weights and widths of the loss (the continuation scales the widths).

    weight: slope of the hinge penalties (per unit of the normalized metric)
    target: fraction of each bound the smooth metrics aim under (margin for the exact model)
    width: surrogate width at scale 1 [fraction of the step]
    smoothing: simulator widths at scale 1 (voltage [V], velocity [m/s], position [m])
    robust_width: temperature of the soft maximum over plants [units of the loss]
    """

    weight: float = 10.0
    target: float = 0.9
    width: float = 4e-3
    smoothing: Smoothing = Smoothing(voltage=0.2, velocity=5e-3, position=1e-5)
    robust_width: float = 0.02


def gains_from_theta(theta, fixed, free_mask):
    """(kp, kd, ki) from log gains ``theta`` (free entries) and ``fixed`` values (the rest)."""
    return jnp.where(free_mask, jnp.exp(theta), fixed)


def controller_with(controller, gains):
    """``controller`` with kp, kd, ki from ``gains`` (array of 3, order kp, kd, ki)."""
    return dataclasses.replace(controller, kp=gains[0], kd=gains[1], ki=gains[2])


def plant_loss(
    gains, plant, controller, experiment, spec: Spec, settings: LossSettings, scale, substeps=None
):
    """(loss, SmoothStepInfo) of one gain set (kp, kd, ki) on one plant, at continuation
    ``scale`` (widths = scale x their values in ``settings``)."""
    smoothing = settings.smoothing.scaled(scale)
    response = simulate(
        plant,
        controller_with(controller, gains),
        experiment,
        smoothing=smoothing,
        substeps=substeps,
    )
    info = smooth_step_info(response, width=settings.width * scale, band=spec.band)
    ts = info.settling_time / spec.settling_time
    os = info.overshoot / spec.overshoot
    # Where the run never settles, the settling surrogate is flat at the horizon: the band
    # excess after the settling bound still says which way is in.
    excess = band_excess(
        response.time,
        response.position,
        response.reference,
        after=settings.target * spec.settling_time,
        band=spec.band,
    )
    penalty = jax.nn.relu(os - settings.target) + jax.nn.relu(ts - settings.target) + excess
    loss = ts + settings.weight * penalty
    # A run that blew up gets a large finite loss (its gradient is discarded by the caller).
    loss = jnp.where(response.diverged | ~jnp.isfinite(loss), 1e3, loss)
    return loss, info


def make_loss(
    controller, experiment, spec: Spec, settings: LossSettings, *, robust: bool, substeps=None
):
    """loss(theta, fixed, free_mask, plants, scale) -> (loss, aux) for one start.

    theta: log gains (3,) (entries where ``free_mask`` is False are ignored); fixed: gains
    (kp, kd, ki) used where ``free_mask`` is False; scale: continuation factor of the widths.
    ``plants`` is one Plant (aux: SmoothStepInfo), or for robust tuning a Plant whose leaves
    carry a leading axis of plant samples: the loss is then the soft maximum over them (aux:
    (per-plant loss, SmoothStepInfo per plant)). Everything but the static configuration is an
    argument, so one compiled function serves every start, bound and continuation stage.
    """

    def one(theta, fixed, free_mask, plant, scale):
        gains = gains_from_theta(theta, fixed, free_mask)
        return plant_loss(
            gains, plant, controller, experiment, spec, settings, scale, substeps=substeps
        )

    if not robust:
        return one

    def worst(theta, fixed, free_mask, plants, scale):
        losses, infos = jax.vmap(one, in_axes=(None, None, None, 0, None))(
            theta, fixed, free_mask, plants, scale
        )
        return soft_max(losses, settings.robust_width), (losses, infos)

    return worst


def batched_value_and_grad(loss):
    """Loss and gradient w.r.t. theta for a batch of starts theta (S, 3): one vmapped call,
    ``(theta, fixed, free_mask, plants, scale) -> ((sum, (losses (S,), aux)), grad (S, 3))``."""

    def total(theta, fixed, free_mask, plants, scale):
        values, aux = jax.vmap(loss, in_axes=(0, None, None, None, None))(
            theta, fixed, free_mask, plants, scale
        )
        return jnp.sum(values), (values, aux)

    return jax.value_and_grad(total, has_aux=True)


__all__ = [
    "GAIN_NAMES",
    "Spec",
    "LossSettings",
    "SmoothStepInfo",
    "gains_from_theta",
    "controller_with",
    "plant_loss",
    "make_loss",
    "batched_value_and_grad",
]
