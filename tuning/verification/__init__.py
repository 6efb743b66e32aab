"""An independent generator of recordings, to check jaxcart's estimators on data their own
simulator did not make (issue 32): its own integrator, friction convention and control loop,
and what real recordings carry (jitter, the encoder's phase, drift, a small lag, run-to-run
drive variation, a hand's push of varying shape).

- :mod:`~tuning.verification.truth`: :class:`TrueCart`, every parameter with its unit;
- :mod:`~tuning.verification.physics`: the drive chain, Karnopp/Stribeck friction, RK4;
- :mod:`~tuning.verification.controller`: the lab's discrete PID, written again;
- :mod:`~tuning.verification.experiments`: steps, ramps, square waves, voltages, taps;
- :mod:`~tuning.verification.artefacts`: :class:`Artefacts`, ``REALISTIC`` and ``NONE``;
- :mod:`~tuning.verification.independent_sim`: :func:`simulate` and :func:`run_controller`;
- :mod:`~tuning.verification.writing`: :func:`make_recording` (an experiment file).
"""

from tuning.verification.artefacts import NONE, REALISTIC, Artefacts
from tuning.verification.independent_sim import (
    ControllerRun,
    Run,
    StepMetrics,
    run_controller,
    simulate,
    step_metrics,
)
from tuning.verification.truth import TrueCart
from tuning.verification.writing import Recording, make_recording, write_run

__all__ = [
    "NONE",
    "REALISTIC",
    "Artefacts",
    "ControllerRun",
    "Recording",
    "Run",
    "StepMetrics",
    "TrueCart",
    "make_recording",
    "run_controller",
    "simulate",
    "step_metrics",
    "write_run",
]
