"""jaxcart: a differentiable simulator and auto-tuner for the cart-on-a-track servo lab.

Public names load on first use (``jaxcart.simulate`` imports JAX then), so that importing a
submodule without JAX, such as :mod:`jaxcart.errors` for the command line, stays instant.
Importing jaxcart changes nothing in the process: no environment variable, no JAX setting, no
thread (:mod:`jaxcart.xlaflags` and :mod:`jaxcart.cache` change them when asked, as the command
line asks on the user's behalf).
"""

from __future__ import annotations

import importlib

#: public name -> module that defines it
_EXPORTS = {
    "PID": "hw.control_law",
    "PIDState": "hw.control_law",
    "pid_init": "hw.control_law",
    "pid_update": "hw.control_law",
    "REGISTRY": "jaxcart.effects",
    "Coulomb": "jaxcart.effects",
    "CoulombAsymmetry": "jaxcart.effects",
    "CurrentLimit": "jaxcart.effects",
    "Deadzone": "jaxcart.effects",
    "DeadzoneAsymmetry": "jaxcart.effects",
    "Delay": "jaxcart.effects",
    "Effect": "jaxcart.effects",
    "Quantization": "jaxcart.effects",
    "Saturation": "jaxcart.effects",
    "Spring": "jaxcart.effects",
    "Stiction": "jaxcart.effects",
    "Stribeck": "jaxcart.effects",
    "Tilt": "jaxcart.effects",
    "TrackFriction": "jaxcart.effects",
    "ViscousAsymmetry": "jaxcart.effects",
    "VoltageOffset": "jaxcart.effects",
    "Experiment": "jaxcart.experiments",
    "ramp": "jaxcart.experiments",
    "reference_sequence": "jaxcart.experiments",
    "setpoints": "jaxcart.experiments",
    "step": "jaxcart.experiments",
    "tap": "jaxcart.experiments",
    "voltage_ramp": "jaxcart.experiments",
    "voltage_sequence": "jaxcart.experiments",
    "voltage_step": "jaxcart.experiments",
    "ENCODER_RESOLUTION": "jaxcart.params",
    "Plant": "jaxcart.params",
    "handout_plant": "jaxcart.plantspec",
    "tap_plant": "jaxcart.plantspec",
    "voltage_limit": "jaxcart.params",
    "build_plant": "jaxcart.plantspec",
    "read_plant_file": "jaxcart.plantspec",
    "write_plant_file": "jaxcart.plantspec",
    "closed_loop": "jaxcart.control_systems",
    "controller_ss": "jaxcart.control_systems",
    "controller_tf": "jaxcart.control_systems",
    "plant_ss": "jaxcart.control_systems",
    "plant_tf": "jaxcart.control_systems",
    "write_mat_experiment": "jaxcart.matfile",
    "EXACT_FORMS": "jaxcart.smooth_sim",
    "LoopState": "jaxcart.smooth_sim",
    "Response": "jaxcart.smooth_sim",
    "IncompatibleRun": "jaxcart.runcheck",
    "Chunked": "jaxcart.simulation",
    "Exact": "jaxcart.simulation",
    "Smooth": "jaxcart.simulation",
    "simulate": "jaxcart.simulation",
    "substeps_per_sample": "jaxcart.substeps",
    "Smoothing": "jaxcart.smoothing",
    "StepInfo": "jaxcart.metrics",
    "step_info": "jaxcart.metrics",
    "step_metrics": "jaxcart.metrics",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'jaxcart' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    if module == "hw.control_law":
        importlib.import_module("jaxcart.pytrees")  # PID as a pytree before anyone uses it
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
