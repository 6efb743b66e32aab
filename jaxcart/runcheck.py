"""The one set of checks that a plant, a controller and an experiment can run together, and
its one error type; every simulator (smooth, exact, chunked) calls :func:`check_run`."""

from __future__ import annotations

from jaxcart.errors import UserError


class IncompatibleRun(UserError):
    """A plant, controller and experiment that cannot be simulated together (the message says
    which value to change)."""


def check_run(plant, controller, experiment) -> None:
    """Raise :class:`IncompatibleRun` when the three cannot run together: a closed-loop
    experiment without a controller, a controller whose sample time [s] differs from the
    experiment's, an effect that cannot run at the sample time (a delay longer than its line).
    The sample time is static, so this runs at trace time, never on traced values."""
    ts = experiment.sample_time
    if experiment.kind == "closed_loop":
        if controller is None:
            raise IncompatibleRun(
                "a closed-loop experiment needs a controller (a jaxcart.PID), got None"
            )
        if abs(controller.sample_time - ts) > 1e-12 * ts:
            raise IncompatibleRun(
                f"controller sample_time {controller.sample_time} s differs from the "
                f"experiment's {ts} s; simulate them at one sample time"
            )
    for effect in plant.effects:
        try:
            effect.check(ts)
        except IncompatibleRun:
            raise
        except ValueError as exc:
            raise IncompatibleRun(" ".join(str(exc).split())) from None
