"""How ``jaxcart fit --cross`` runs across processes (jax.distributed): each process fits its
share of the recordings alone and cross-predicts the others with them; the rows are gathered on
every process (:class:`tuning.distributed.Exchange`), which then holds the single-process table.

The unit of work is one recording: fitting it alone and predicting every other recording with
its values (``len(recordings)`` fits, independent of every other unit). Process ``i`` of ``n``
computes the units :meth:`~tuning.distributed.Exchange.items` gives it (every ``n``-th from
``i``);
the rows (names and a few numbers, under 1 kB each) travel as JSON bytes in one all-gather and
are put back in the single-process order. JSON writes a float's shortest repr, which reads back
as the same float, so the gathered numbers are those the other process computed, bit for bit.

The joint fit of all recordings (``jaxcart fit`` without ``--cross``) is one problem; process 0
alone computes it while the others fit their rows. An error one process meets (a recording it
cannot fit, process 0's joint fit or output check) travels in the same all-gather in place of
its rows (:meth:`tuning.distributed.Exchange.allgather`) and is raised on every process, so none
waits for a partner that has stopped.
"""

from __future__ import annotations

import json

import numpy as np


def cross_rows(rec, recordings, params, *, progress=False, executor=None) -> list:
    """Fit ``rec`` alone; predict every one of ``recordings`` with those values (its start
    state refitted). One row per recording, in their order (see :func:`cross_table`)."""
    # lazy: these import jax and the fit, 0.5 s at start-up (python -X importtime), and
    # `jaxcart fit`'s parser imports this module: its --help starts no jax
    from tuning.estimation import fit
    from tuning.estimation.engine.segments import recording_name
    from tuning.estimation.fitting.result import _finite

    alone = fit.fit([rec], params, progress=progress, executor=executor)
    values = {n: float(alone.values[fit.canonical(n)]) for n in params}
    held = [n for n, e in alone.params.items() if not e.identifiable]
    rows = []
    for other in recordings:
        if other is rec:
            pred = alone
        else:
            pred = fit.cross_predict(values, [other], progress=progress, executor=executor)
        rows.append(
            {
                "fitted_on": recording_name(rec),
                "predicting": recording_name(other),
                "rms": _finite(pred.rms_after_exact),
                "rms_smooth": _finite(pred.rms_after),
                "values": values,
                "held": held,
            }
        )
    return rows


def cross_table(
    recordings, params, *, progress=False, processes=None, failure=None, executor=None
) -> list:
    """Fit each recording alone; predict every other one with those values (its start state
    refitted). [{"fitted_on", "predicting", "rms", "rms_smooth", "values", "held"}] with RMS
    [m], grouped by the recording fitted, in the recordings' order; "held" names the
    parameters that recording could not identify (kept at their start).

    processes: a :class:`tuning.distributed.Exchange` of a jax.distributed run: this process
    fits its share of the recordings and every process returns the whole table. failure: an
    exception this process met before (process 0's joint fit): it computes nothing more and
    the error is raised on every process after the exchange, as is one met in a fit.
    executor: makes each fit's exact runs (:func:`tuning.estimation.fit.fit`)."""
    recordings = list(recordings)

    def group(i):
        return cross_rows(recordings[i], recordings, params, progress=progress, executor=executor)

    if processes is None:
        if failure is not None:
            raise failure
        return [row for i in range(len(recordings)) for row in group(i)]
    mine: dict = {}
    rank = -1  # a failure before the table: first, as the joint fit runs first in one process
    if failure is None:
        try:
            for rank in processes.items(len(recordings)):
                mine[str(rank)] = group(rank)
        except Exception as exc:  # sent in place of the rows: the others must not wait
            failure = exc
    groups = share(processes, mine, failure, rank=rank)
    return [row for i in range(len(recordings)) for row in groups[str(i)]]


def share(processes, doc: dict, failure=None, *, rank: int = -1) -> dict:
    """Every process's ``doc`` (JSON-able, keys distinct over the processes), merged. Where a
    process passes a ``failure`` (an exception), every process raises instead the
    :class:`~jaxcart.errors.UserError` of least ``rank`` (the work item it came from: the
    error a single process meets first; see :meth:`tuning.distributed.Exchange.allgather`)."""
    data = np.frombuffer(json.dumps(doc).encode(), dtype=np.uint8)
    merged: dict = {}
    for part in processes.allgather({"json": data}, failure=failure, rank=rank):
        merged.update(json.loads(part["json"].tobytes().decode()))
    return merged
