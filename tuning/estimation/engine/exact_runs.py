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
from jaxcart.workers import SERIAL


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
    """``run`` (an array, or a tuple of arrays and None: a residual and its command) with its
    arrays read-only (a memo shares them; those a helper process sends back arrive
    writable)."""
    for a in run if isinstance(run, tuple) else (run,):
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


class ExactMemo:
    """The last ``size`` exact runs of one diagnosis or fit, by candidate structure and values:
    the polish re-runs points it has run (a trial it accepted is the next iteration's start, the
    polished point is re-checked), about a quarter of a diagnosis's exact runs (measured on
    the built-in P 50 step: 247 runs, 189 distinct). Results are shared: read-only arrays.
    ``run``: what one recording's job makes (:func:`exact_run`, a diagnosis's; a fit's
    :func:`exact_position`)."""

    def __init__(self, size: int = 64, executor=None, run=None):
        self.size = size
        self.executor = executor or SERIAL  # makes the runs of fill several at a time
        self.run = run or exact_run
        self.runs: dict = {}
        self.hits = 0
        self.made = 0  # single runs simulated (here or by a helper process)
        # One recording's run by its own plant and start: a parameter that does not act on a
        # recording (a per-run copy of another run, a drive limit on the unplugged tap) leaves
        # its run as it was, so a forward difference re-simulates only the runs it moves.
        self.one: dict = {}

    def segment(self, key, compute):
        """One recording's exact run, by (index, plant, y0, yd0)."""
        if key in self.one:
            self.hits += 1
            self.one[key] = self.one.pop(key)
            return self.one[key]
        return self._store(key, compute())

    def fill(self, jobs, sizes=None) -> None:
        """Make the runs of ``jobs`` ((key, job) pairs: an :class:`ExactJob`, or what ``run``
        takes) not stored yet, all at once (the executor's ``map``: several at a time, in
        helper processes); ``sizes``: each job's samples (default its target's)."""
        todo, cost = {}, {}
        for n, (key, job) in enumerate(jobs):
            if key not in self.one and key not in todo:
                todo[key] = job
                cost[key] = job.target.size if sizes is None else sizes[n]
        made = self.executor.map(self.run, list(todo.values()), list(cost.values()))
        for key, out in zip(todo, made, strict=True):
            self._store(key, out)

    def _store(self, key, out):
        self.made += 1
        self.one[key] = out = read_only(out)
        if len(self.one) > 4 * self.size:
            del self.one[next(iter(self.one))]
        return out

    def get(self, cand, values, compute):
        key = (
            tuple(cand.parts),
            tuple(cand.corrections),
            values_key(values),
        )
        if key in self.runs:
            self.hits += 1
            self.runs[key] = self.runs.pop(key)  # most recent last
            return self.runs[key]
        out = compute()
        for group in out:
            read_only(tuple(group))
        self.runs[key] = out
        if len(self.runs) > self.size:
            del self.runs[next(iter(self.runs))]
        return out


def values_key(values: dict) -> tuple:
    """``values`` as a key (names and floats, sorted)."""
    return tuple(sorted((k, float(v)) for k, v in values.items()))
