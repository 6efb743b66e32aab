"""How a grid runs: fixed blocks of points, checkpoint files keyed by the problem, the share of
each process of a distributed run, and the streaming reduction to the best point.

A grid of n points is cut into blocks of :data:`BLOCK` points (flat index order). Every block's
metrics are kept in a :class:`BlockStore`: in memory for a small grid, else one ``.npz`` per
block in a folder named by a hash of the problem (plant, controller, experiment, smoothing,
precision, axes, block size), so a killed run resumes with the blocks it finished and a
changed problem never reuses stale ones. With several processes (:mod:`jaxcart.parallel`)
each computes its :func:`jaxcart.parallel.partition` of the blocks on its local devices and
publishes them to process 0, which stores them and reduces. The reduction reads the blocks in
order and keeps only summaries (the best point, feasible counts per k_i slice, settling-time
range), plus the full metric arrays when the grid is small enough (:data:`FULL_LIMIT`).
"""

from __future__ import annotations

import hashlib
import io
import os
import shutil
import tempfile
import weakref
from pathlib import Path

import jax
import numpy as np

from jaxcart import parallel
from jaxcart.errors import UserError
from jaxcart.metrics import StepInfo

#: Points per block: the unit of checkpointing, distribution and progress (independent of the
#: device count, so blocks of a run resumed on another machine still match).
BLOCK = 65536
#: Grids up to this many points keep every metric array in memory (about 30 bytes per point in
#: float32); larger ones keep summaries and read slices back from the block files.
FULL_LIMIT = 1 << 22
#: Bump when the block contents change meaning: old checkpoints are then never reused.
FORMAT = 1


def problem_key(*parts) -> str:
    """Hex digest of pytrees and plain values: array leaves by dtype, shape and bytes, the
    tree structure (class names, static fields) by its text."""
    h = hashlib.sha256(f"jaxcart-grid-{FORMAT}-{jax.__version__}".encode())
    for part in parts:
        leaves, treedef = jax.tree_util.tree_flatten(part)
        h.update(str(treedef).encode())
        for leaf in leaves:
            a = np.asarray(leaf)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:20]


class BlockStore:
    """Each block's metrics ({name: array}) under ``folder/<key>/block-NNNNNN.npz`` (written
    atomically: a killed run leaves whole blocks or none), or in memory when ``folder`` is
    None."""

    def __init__(self, folder, key: str):
        self.key = key
        self.dir = None if folder is None else Path(folder) / key
        self._memory: dict[int, bytes] = {}
        if self.dir is not None:
            try:
                self.dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise UserError(
                    f"checkpoint folder {self.dir}: cannot create it ({exc.strerror}); "
                    "choose another with --checkpoint"
                ) from None

    def _path(self, i: int) -> Path:
        return self.dir / f"block-{i:06d}.npz"

    def has(self, i: int) -> bool:
        return i in self._memory if self.dir is None else self._path(i).is_file()

    def count(self) -> int:
        """Blocks already stored (e.g. by an interrupted run)."""
        if self.dir is None:
            return len(self._memory)
        return sum(1 for _ in self.dir.glob("block-*.npz"))

    def write_bytes(self, i: int, data: bytes) -> None:
        if self.dir is None:
            self._memory[i] = data
            return
        tmp = self._path(i).with_suffix(f".tmp{os.getpid()}")
        tmp.write_bytes(data)
        os.replace(tmp, self._path(i))

    def read_bytes(self, i: int) -> bytes:
        return self._memory[i] if self.dir is None else self._path(i).read_bytes()

    def save(self, i: int, arrays: dict) -> None:
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        self.write_bytes(i, buf.getvalue())

    def load(self, i: int, names=None) -> dict:
        """Block i's arrays (only ``names`` when given: the others are not even read)."""
        source = io.BytesIO(self._memory[i]) if self.dir is None else self._path(i)
        with np.load(source) as data:
            return {name: data[name] for name in (names or data.files)}

    def remove(self) -> None:
        """Delete the blocks (after the outputs are written)."""
        self._memory.clear()
        if self.dir is not None:
            shutil.rmtree(self.dir, ignore_errors=True)
            try:
                self.dir.parent.rmdir()  # the checkpoint folder too, once empty
            except OSError:
                pass


def temporary_store(key: str) -> BlockStore:
    """A store in a temporary folder, deleted with the store (a large grid, no checkpoint)."""
    folder = tempfile.mkdtemp(prefix="jaxcart-grid-")
    store = BlockStore(folder, key)
    weakref.finalize(store, shutil.rmtree, folder, True)
    return store


def fill(
    store: BlockStore, n: int, block: int, compute, *, progress=None, say=None, timeout_s=3600.0
):
    """Make every block of ``n`` points present in ``store``; True on process 0 (which then
    holds them all), False on the other processes of a distributed run.

    ``compute(i)`` returns block i's {name: array}. Blocks already stored are not recomputed
    (``say(text)`` tells how many were found). ``progress(done, total)`` counts the points this
    process computes as they complete. Returns (process 0?, points computed here)."""
    n_blocks = -(-n // block)
    me, count = parallel.process_index(), parallel.process_count()
    mine = parallel.partition(n_blocks, me, count)
    todo = [i for i in mine if not store.has(i)]
    if say is not None and len(todo) < len(mine):
        say(
            f"resuming: {len(mine) - len(todo)} of {len(mine)} blocks already computed "
            f"in {store.dir}"
        )
    share = sum(min(block, n - i * block) for i in todo)
    done = 0
    todo_set = set(todo)
    # In block order, process 0 collecting the others' blocks between its own: the runtime's
    # store then holds about one block per process at a time, whatever the grid's size.
    for i in range(n_blocks):
        key = f"jaxcart-grid/{store.key}/{i}"
        if i in mine:
            if i in todo_set:
                store.save(i, compute(i))
                done += min(block, n - i * block)
                if progress is not None:
                    progress(done, share)
            if me != 0:
                _exchange(i, parallel.publish, key, store.read_bytes(i))
        elif me == 0:
            # Always fetch (it deletes the key), also when a shared folder already has it.
            data = _exchange(i, parallel.fetch, key, timeout_s)
            if not store.has(i):
                store.write_bytes(i, data)
    return me == 0, share


def _exchange(i: int, step, *args):
    """``step(*args)``: one publish or fetch of block ``i``; a failure of the runtime is one
    line, not a trace."""
    try:
        return step(*args)
    except Exception as exc:  # the runtime raises its own types (timeouts, lost peers)
        raise UserError(
            f"distributed grid: block {i} could not be exchanged with process 0 "
            f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); check that "
            "every process runs the same command and that the coordinator is reachable"
        ) from None


def blocks(store: BlockStore, n: int, block: int, names=None):
    """(start, {name: array}) of every block in order (only ``names`` when given)."""
    for i in range(-(-n // block)):
        yield i * block, store.load(i, names)


def feasible_mask(flat, settling_spec, overshoot_spec) -> np.ndarray:
    """True where a point meets the specification (settles in time, small overshoot, not
    diverged): :meth:`jaxcart.StepInfo.meets` on arrays."""
    ts, os_, bad = flat["settling_time"], flat["overshoot"], flat["diverged"]
    return ~bad & (ts < settling_spec) & (os_ < overshoot_spec)


def best_of(flat, feasible, settling_spec, overshoot_spec) -> tuple[int, bool]:
    """Flat index of the best point and whether it is feasible.

    Feasible: smallest settling time, ties (times are whole samples) broken by overshoot.
    None feasible: smallest relative violation max(0, ts/spec - 1) + max(0, os/spec - 1), ties
    (e.g. all never settle) broken by steady-state error, then overshoot; diverged runs last.
    Remaining ties go to the lowest index, so the best of blocks' bests is the best of all.
    """
    ts, os_ = flat["settling_time"], flat["overshoot"]
    if feasible.any():
        candidates = np.flatnonzero(feasible & (ts == ts[feasible].min()))
        return int(candidates[np.argmin(os_[candidates])]), True
    with np.errstate(invalid="ignore"):
        violation = np.maximum(0, ts / settling_spec - 1) + np.maximum(0, os_ / overshoot_spec - 1)
    violation = np.where(np.isnan(violation), np.inf, violation)
    pool = ~flat["diverged"] if not flat["diverged"].all() else np.ones_like(feasible)
    candidates = np.flatnonzero(pool & (violation == violation[pool].min()))
    order = np.lexsort((os_[candidates], flat["steady_state_error"][candidates]))
    return int(candidates[order[0]]), False


class Reducer:
    """Streaming summaries of blocks given in flat order (see :func:`best_of`).

    keep_full: also keep every metric array (n points); nki: the k_i axis length of a grid
    (feasible points counted per k_i slice), None for a list.
    """

    def __init__(self, n, dtype, settling_spec, overshoot_spec, *, keep_full, nki=None):
        self.spec = (settling_spec, overshoot_spec)
        self.nki = nki
        self.winners: list[tuple[int, bool, dict]] = []
        self.n_feasible = 0
        self.ki_feasible = np.zeros(nki or 1, np.int64)
        self.finite = [np.inf, -np.inf]  # finite settling times: min, max [s]
        self.full = None
        if keep_full:
            self.full = {name: np.empty(n, dtype) for name in StepInfo._fields}
            self.full["diverged"] = np.empty(n, bool)
            self.full["feasible"] = np.empty(n, bool)

    def add(self, start: int, flat: dict) -> None:
        ok = feasible_mask(flat, *self.spec)
        index, is_feasible = best_of(flat, ok, *self.spec)
        self.winners.append(
            # A copy, not a view: a view would keep every block's arrays alive.
            (start + index, is_feasible, {k: v[index : index + 1].copy() for k, v in flat.items()})
        )
        self.n_feasible += int(ok.sum())
        if self.nki is not None:
            k = (start + np.flatnonzero(ok)) % self.nki
            self.ki_feasible += np.bincount(k, minlength=self.nki)
        ts = flat["settling_time"][np.isfinite(flat["settling_time"])]
        if ts.size:
            self.finite = [
                min(self.finite[0], float(ts.min())),
                max(self.finite[1], float(ts.max())),
            ]
        if self.full is not None:
            stop = start + ok.size
            for name, values in flat.items():
                self.full[name][start:stop] = values
            self.full["feasible"][start:stop] = ok

    def best(self) -> tuple[int, bool, dict]:
        """(flat index, feasible, {name: value}) of the best point of every block added."""
        feasible = np.array([w[1] for w in self.winners])
        pool = [w for w in self.winners if w[1]] if feasible.any() else self.winners
        flat = {k: np.concatenate([w[2][k] for w in pool]) for k in pool[0][2]}
        index, is_feasible = best_of(flat, np.array([w[1] for w in pool]), *self.spec)
        return pool[index][0], is_feasible, {k: v[index].item() for k, v in flat.items()}
