"""jaxcart: a differentiable simulator and auto-tuner for the cart-on-a-track servo lab."""

import jax as _jax

from hw.control_law import PID, PIDState, pid_init, pid_update
from jaxcart.effects import Coulomb, Effect, Saturation
from jaxcart.experiments import (
    Experiment,
    ramp,
    reference_sequence,
    setpoints,
    step,
    tap,
    voltage_ramp,
    voltage_sequence,
    voltage_step,
)
from jaxcart.params import ENCODER_RESOLUTION, Plant, handout_plant, tap_plant
from jaxcart.simulate import EXACT_FORMS, Response, simulate
from jaxcart.smoothing import Smoothing

# The controller settings live in hw/ (numpy only); register them as a pytree here.
_jax.tree_util.register_dataclass(
    PID,
    data_fields=["kp", "ki", "kd", "tau", "v_limit", "kb"],
    meta_fields=["sample_time", "derivative_on", "anti_windup"],
)

from jaxcart.metrics import StepInfo, step_info, step_metrics  # noqa: E402

__all__ = [
    "PID",
    "PIDState",
    "pid_init",
    "pid_update",
    "Coulomb",
    "Effect",
    "Saturation",
    "Experiment",
    "ramp",
    "reference_sequence",
    "setpoints",
    "step",
    "tap",
    "voltage_ramp",
    "voltage_sequence",
    "voltage_step",
    "ENCODER_RESOLUTION",
    "Plant",
    "handout_plant",
    "tap_plant",
    "EXACT_FORMS",
    "Response",
    "simulate",
    "Smoothing",
    "StepInfo",
    "step_info",
    "step_metrics",
]
