"""Long simulations: what they will cost, said before they start, and progress while they run.

A 10-million-sample recording or ``--horizon 1e5`` ran for minutes without a word. Here the
smooth simulator runs the same loop (:func:`jaxcart.smooth_sim.loop`) in chunks of ``CHUNK``
samples, one compiled scan carried from chunk to chunk (the same steps as one scan over the
whole signal), so that after the first chunks the rate is known and the cost is printed; the
exact simulator is timed on a prefix. Runs that would not fit in memory are refused before
they start, with the horizon that would.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart.errors import UserError
from jaxcart.exact import simulate_exact
from jaxcart.smooth_sim import DIVERGED_POSITION, Response, loop

#: Samples per compiled chunk of a long smooth run.
CHUNK = 1 << 16
#: Runs longer than this many samples go through the chunked path (with progress).
LONG_SAMPLES = 4 * CHUNK
#: Announce the cost when the run is expected to take longer than this [s].
ANNOUNCE_SECONDS = 60.0
#: Bytes held per sample: the response's 8 float64 traces, the CSV block and the plot's copy.
BYTES_PER_SAMPLE = 8 * 8 * 2
#: Bytes of CSV output per sample and column (shortest exact float text and a comma).
CSV_BYTES_PER_VALUE = 19
#: Samples of the exact simulator's timing run.
EXACT_PROBE = 2000
#: Values the CSV writer formats per second (hw.csvio, measured on the shared 2-core CPU:
#: 5e6 values in 5-9 s), for the cost announced before a run.
WRITE_VALUES_PER_S = 0.7e6


def memory_budget() -> float:
    """Half the machine's physical memory [bytes] (inf where unknown)."""
    try:
        return 0.5 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return math.inf


def check_size(n_samples: int, sample_time: float, what: str) -> None:
    """Refuse (UserError) a run whose traces would not fit in half the memory."""
    need = n_samples * BYTES_PER_SAMPLE
    budget = memory_budget()
    if need > budget:
        longest = budget / BYTES_PER_SAMPLE * sample_time
        raise UserError(
            f"{what}: {n_samples:.3g} samples need about {_bytes(need)} of memory, more than "
            f"half of this machine's; give --horizon {longest:.3g} (s) or less"
        )


def output_bytes(n_samples: int, n_columns: int) -> float:
    """About how large the run's CSV will be [bytes]."""
    return float(n_samples) * n_columns * CSV_BYTES_PER_VALUE


def write_seconds(n_samples: int, n_columns: int) -> float:
    """About how long writing the run's CSV will take [s]."""
    return float(n_samples) * n_columns / WRITE_VALUES_PER_S


def announce(seconds: float, n_samples: int, n_columns: int, sample_time: float, out=None):
    """Print the expected cost on stderr when it is more than ``ANNOUNCE_SECONDS``: ``seconds``
    of simulation plus the writing of the output."""
    seconds += write_seconds(n_samples, n_columns)
    if seconds <= ANNOUNCE_SECONDS:
        return False
    out = sys.stderr if out is None else out
    print(
        f"simulate: about {duration_text(seconds)} for {n_samples:.3g} samples "
        f"({(n_samples - 1) * sample_time:g} s simulated), "
        f"{_bytes(output_bytes(n_samples, n_columns))} of output; --horizon to shorten",
        file=out,
        flush=True,
    )
    return True


def simulate_chunked(plant, controller, experiment, *, chunk=None, n_columns=5, out=None):
    """:func:`jaxcart.simulate` in chunks of ``chunk`` samples with progress on stderr (numpy
    arrays in the :class:`jaxcart.Response`). The cost is announced after the second chunk
    (the first compiles) when the rest and the writing are expected to take more than a
    minute."""
    out = sys.stderr if out is None else out
    chunk = CHUNK if chunk is None else int(chunk)
    n = experiment.n_samples
    signal = np.asarray(experiment.signal)
    init, step = loop(plant, controller, experiment)
    run = jax.jit(lambda carry, xs: jax.lax.scan(step, carry, xs))
    names = ("position", "velocity", "reference", "command", "voltage", "unlimited")
    traces = {name: np.empty(n) for name in names}
    carry = init
    start = time.perf_counter()
    chunk_start = start
    told, reported = False, 0.0
    for k0 in range(0, n, chunk):
        k1 = min(n, k0 + chunk)
        xs = signal[k0:k1]
        if xs.size < chunk:  # pad the last chunk: one compiled shape
            xs = np.concatenate([xs, np.full(chunk - xs.size, xs[-1])])
        carry, s = run(carry, jnp.asarray(xs))
        for name in names:
            traces[name][k0:k1] = np.asarray(getattr(s, name))[: k1 - k0]
        now = time.perf_counter()
        if k0 // chunk == 1 and not told:
            rate = chunk / max(now - chunk_start, 1e-9)
            told = announce((n - k1) / rate, n, n_columns, experiment.sample_time, out)
        chunk_start = now
        fraction = k1 / n
        if fraction - reported >= 0.1 or k1 == n:
            reported = fraction
            print(
                f"simulate: {fraction:.0%} ({k1} of {n} samples, {now - start:.0f} s)",
                file=out,
                flush=True,
            )
        y = traces["position"][k0:k1]
        if not np.all(np.isfinite(y)) or np.any(np.abs(y) > DIVERGED_POSITION):
            for name in names:
                traces[name][k1:] = np.nan
            break
    y = traces["position"]
    bad = ~np.isfinite(y) | (np.abs(y) > DIVERGED_POSITION)
    return Response(
        time=np.arange(n) * experiment.sample_time,
        position=y,
        velocity=traces["velocity"],
        reference=traces["reference"],
        error=traces["reference"] - y,
        command=traces["command"],
        voltage=traces["voltage"],
        diverged=np.asarray(bool(np.any(bad))),
        unlimited=traces["unlimited"],
        kind=experiment.kind,
    )


def estimate_exact(plant, controller, experiment) -> float:
    """Seconds the exact simulator will take for the whole experiment, from a timed prefix."""
    n = experiment.n_samples
    probe = min(n, EXACT_PROBE)
    short = dataclasses.replace(experiment, signal=experiment.signal[:probe])
    start = time.perf_counter()
    simulate_exact(plant, controller, short)
    return (time.perf_counter() - start) * n / probe


def duration_text(seconds: float) -> str:
    """A duration as a person reads it: "45 s", "12 min", "1.5 h"."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _bytes(n: float) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n:.0f} B"


#: Points per curve in a figure: a 1040-pixel-wide plot shows no more.
PLOT_POINTS = 20_000


def thin_indices(n: int, *series, points: int = PLOT_POINTS) -> np.ndarray:
    """Indices of at most about ``points`` samples of ``n`` that keep, in each block, the
    minimum and maximum of every series (a figure of the thinned curves shows the same
    envelope); all of them when n <= points."""
    if n <= points:
        return np.arange(n)
    per = 1 + 2 * len(series)  # each block's start, and the extremes of each series
    k = int(math.ceil(n * per / points))
    blocks = n // k
    keep = [np.arange(blocks) * k, [n - 1]]
    for values in series:
        if values is None:
            continue
        body = np.asarray(values, dtype=float)[: blocks * k].reshape(blocks, k)
        base = np.arange(blocks) * k
        keep += [base + np.nanargmin(body, axis=1), base + np.nanargmax(body, axis=1)]
        tail = np.asarray(values, dtype=float)[blocks * k :]
        if tail.size and np.isfinite(tail).any():  # the last, partial block's extremes too
            keep += [[blocks * k + np.nanargmin(tail)], [blocks * k + np.nanargmax(tail)]]
    return np.unique(np.concatenate(keep))
