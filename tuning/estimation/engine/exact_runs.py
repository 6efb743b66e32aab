"""One recording's exact-simulator run as a job a helper process can take
(:meth:`jaxcart.workers.Helpers.map`): small, picklable, and importing only the simulator.

A fit's exact Gauss-Newton makes its runs several at a time: the forward differences' columns,
each recording of a trial. :class:`ExactJob` carries what one run needs, :func:`exact_run`
makes it (the diagnosis's residual and command) and :func:`exact_position` (a fit's
position).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from jaxcart.exact import simulate_exact
from jaxcart.experiments import voltage_sequence


class ExactJob(NamedTuple):
    """One recording's exact run, as a helper process gets it: the controller, the plant and
    the experiment; the measured ``target`` [m]; ``counts_in_loop`` and ``motor`` of its
    :class:`~tuning.estimation.engine.segments.Segment`."""

    controller: object
    plant: object
    experiment: object
    target: np.ndarray
    counts_in_loop: bool
    motor: bool


def exact_run(job: ExactJob):
    """(exact residual [m], command [V] or None) of one recording, read-only arrays."""
    res, pos = _compared(job.plant, job.controller, job.experiment, job.counts_in_loop)
    if not np.all(np.isfinite(pos)):
        pos = np.where(np.isfinite(pos), pos, 1.0)
    u = np.asarray(res.command, dtype=float) if job.motor else None
    return read_only((pos - job.target, u))


def read_only(run):
    """``run`` ((residual, command or None)) with its arrays read-only (a memo shares them;
    those a helper process sends back arrive writable)."""
    for a in run:
        if a is not None:
            a.flags.writeable = False
    return run


def _cart_position(plant, experiment, command) -> np.ndarray:
    """The cart's position [m] under the commands [V] a closed loop sent: the same run replayed
    open loop on the plant without its sensor (the sensor only shapes what the controller
    reads, so the trajectory is the same, float for float). A run whose controller reads
    counts records the counts; their forward differences in a parameter are a staircase."""
    bare = dataclasses.replace(
        plant, effects=tuple(e for e in plant.effects if e.stage != "sensor")
    )
    replay = voltage_sequence(
        np.asarray(command, dtype=float),
        sample_time=float(experiment.sample_time),
        y0=float(experiment.y0),
        yd0=float(experiment.yd0),
    )
    return np.asarray(simulate_exact(bare, None, replay).position, dtype=float)


def exact_position(job) -> np.ndarray:
    """The exact simulator's position [m] of one recording: ``job`` is (plant, controller or
    None, experiment, counts_in_loop); where the controller reads the counts, the cart's own
    position (:func:`_cart_position`), as the diagnosis compares (:func:`exact_run`)."""
    return _compared(*job)[1]


def _compared(plant, controller, experiment, counts_in_loop):
    """(the exact run, the position [m] compared with the recording): what the sensor read,
    or where the controller reads the counts the cart's own position (:func:`_cart_position`)."""
    res = simulate_exact(plant, controller, experiment)
    if counts_in_loop and not res.diverged:
        return res, _cart_position(plant, experiment, res.command)
    return res, np.asarray(res.position, dtype=float)
