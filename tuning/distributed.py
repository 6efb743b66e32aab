"""How a command runs across processes (jax.distributed): each process computes its share of
the work items, and the results are gathered on every process (:class:`Exchange`), which then
takes the single-process decisions.

Used by ``jaxcart tune`` (the batch of starts: :class:`tuning.design.start_share.StartShare`),
``jaxcart diagnose`` (:func:`tuning.estimation.diagnose.diagnose` splits its batch fits, exact
re-checks and exact polishes of the candidates over the processes) and ``jaxcart fit --cross``
(one recording each, :mod:`tuning.estimation.cross_fit`). Process ``i`` of ``n`` computes the
items :func:`jaxcart.parallel.partition` gives it (every ``n``-th from ``i``); the payloads are
small numpy arrays through the runtime's key-value store (:func:`gather_rows` puts the rows of
every process back in order).

Errors travel in the exchange: a process that meets an exception publishes it in its next
exchange call in place of its payload (:meth:`Exchange.carry` around ``jaxcart tune`` and
``jaxcart diagnose``; ``fit --cross`` passes its own, ranked by recording), and every process
raises the same :class:`UserError` there instead of waiting for a partner that has stopped (up
to ``timeout_s``). A process that dies outright is left to the runtime's own checks.
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np

from jaxcart import parallel
from jaxcart.errors import UserError

#: Prefix of the key-value store keys of the exchanged rows.
PREFIX = "jaxcart-exchange"
#: Name of the one array of a payload that carries an error instead of rows: JSON [rank, message].
ERROR = "jaxcart-error"


class Exchange:
    """All-gathers of small numpy payloads between the processes of a jax.distributed run,
    through the runtime's key-value store; every process must make the same calls in the
    same order (they are numbered, not named).

    index, count: this process and the number of processes (default the runtime's).
    timeout_s: the longest wait for another process's payload [s].
    """

    #: Exchanges made in this process: part of the keys, so a second one (a second tune in a
    #: session that joined once) never meets the first one's keys or barrier.
    made = 0

    def __init__(self, index=None, count=None, *, timeout_s: float = 3600.0):
        self.index = parallel.process_index() if index is None else index
        self.count = parallel.process_count() if count is None else count
        self.timeout_s = timeout_s
        self.calls = 0
        #: An error met now is published in the next call (:meth:`carry`); False during a
        #: call, after one raised and after :meth:`finish`.
        self.open = True
        self.finished = False
        self.run = Exchange.made
        Exchange.made += 1

    def items(self, n: int) -> range:
        """The items of ``n`` this process computes (:func:`jaxcart.parallel.partition`)."""
        return parallel.partition(n, self.index, self.count)

    def owners(self, n: int) -> list[range]:
        """Every process's items of ``n``, by process."""
        return [parallel.partition(n, p, self.count) for p in range(self.count)]

    def allgather(self, arrays: dict, *, failure=None, rank: int = 0) -> list[dict]:
        """Every process's ``arrays`` ({name: numpy array}), by process.

        failure: an exception this process met instead of computing ``arrays``, published in
        their place (a :class:`UserError` as it is, any other as one line naming its type).
        Where any process published one, every process raises the same :class:`UserError`:
        the one of least ``rank`` (e.g. the work item it came from), then of least process
        index."""
        if failure is None:
            mine = {k: np.asarray(v) for k, v in arrays.items()}
        else:
            mine = _error_payload(failure, rank, self.index, self.count)
        data = _pack(mine)
        call = self.calls
        self.calls += 1
        self.open = False  # a failure inside the call is the exchange's own: never sent again
        _exchange(parallel.publish, self._key(call, self.index), data)
        parts = []
        for p in range(self.count):
            if p == self.index:
                parts.append(mine)
                continue
            data = _exchange(parallel.fetch, self._key(call, p), self.timeout_s, delete=False)
            parts.append(_unpack(data))
        # Every other process published this call, so it has fetched the previous one: this
        # process's previous payload can go.
        if call > 0:
            _delete(self._key(call - 1, self.index))
        errors = [_error_of(part, p) for p, part in enumerate(parts) if ERROR in part]
        if errors:  # every process stops here, with the same error
            raise UserError(min(errors)[2]) from failure
        self.open = True
        return parts

    def sync(self) -> None:
        """An exchange without rows: every process has come this far, or every process raises
        the error one of them met before it (see :meth:`carry`)."""
        self.allgather({})

    @contextlib.contextmanager
    def carry(self, rank: int = 0):
        """A block whose exceptions reach every process: one this process meets while the
        exchange is open is published in its next call in place of its rows
        (:meth:`allgather`, ``rank``), and raised there on every process as the same
        :class:`UserError`. Errors of the exchange itself (a lost partner, an error another
        process sent) and any after :meth:`finish` go up as they are."""
        try:
            yield self
        except Exception as exc:
            if not self.open:
                raise
            self.allgather({}, failure=exc, rank=rank)  # raises on every process

    def finish(self) -> bool:
        """End the exchange: a last :meth:`sync` (an error met since the last call reaches
        every process), then every process waits for the others; True on process 0."""
        self.sync()
        self.open, self.finished = False, True
        try:
            parallel.barrier(f"{PREFIX}/{self.run}/done", self.timeout_s)
        except Exception as exc:  # the runtime's own types (timeouts, lost peers)
            raise UserError(_lost(exc)) from None
        _delete(self._key(self.calls - 1, self.index))
        return self.index == 0

    def _key(self, call: int, index: int) -> str:
        return f"{PREFIX}/{self.run}/{call}/{index}"


def gather_rows(parts: list[dict], owners: list, n: int) -> dict:
    """{name: array of n rows} from every process's rows (``owners``: their row indices)."""
    out = {}
    for name in parts[0]:
        shaped = next((p[name] for p in parts if p[name].shape[0]), parts[0][name])
        full = np.zeros((n,) + shaped.shape[1:], shaped.dtype)
        for part, rows in zip(parts, owners, strict=True):
            full[np.asarray(rows, dtype=int)] = part[name]
        out[name] = full
    return out


def _delete(key: str) -> None:
    """Remove this process's own ``key`` from the store (read back at once: it is there)."""
    try:
        parallel.fetch(key, 60.0)
    except Exception:  # the store is only cleaned: a failure here costs nothing
        pass


def _pack(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _unpack(data: bytes) -> dict:
    with np.load(io.BytesIO(data)) as z:
        return {k: z[k] for k in z.files}


def _error_payload(exc, rank: int, index: int, count: int) -> dict:
    """The payload that carries ``exc``: a :class:`UserError`'s message as it is, any other
    exception as one line naming its type and process (its traceback stays here, as the
    cause of the error raised)."""
    if isinstance(exc, UserError):
        message = str(exc)
    else:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else "(no message)"
        message = f"{type(exc).__name__} in process {index} of {count}: {first}"
    text = json.dumps([int(rank), message])
    return {ERROR: np.frombuffer(text.encode(), dtype=np.uint8)}


def _error_of(part: dict, index: int) -> tuple:
    """(rank, process index, message) of a payload that carries an error: its order."""
    rank, message = json.loads(part[ERROR].tobytes())
    return rank, index, message


def _lost(exc) -> str:
    first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return (
        f"distributed run: results could not be exchanged between the processes ({first}); "
        "check that every process runs the same command and that the coordinator is reachable"
    )


def _exchange(step, *args, **kwargs):
    """``step(*args)``: one publish or fetch; a failure of the runtime is one line."""
    try:
        return step(*args, **kwargs)
    except Exception as exc:  # the runtime raises its own types (timeouts, lost peers)
        raise UserError(_lost(exc)) from None


def spread(processes, items, compute):
    """``[compute(item) for item in items]``, each a ({name: float}, [arrays]) pair; with
    ``processes`` (a :class:`tuning.distributed.Exchange`) each item computed by one process and
    every result gathered on every process."""
    if processes is None:
        return [compute(item) for item in items]
    mine = {}
    for i in processes.items(len(items)):
        values, arrays = compute(items[i])
        mine[f"n/{i}"] = np.array(len(arrays))
        mine[f"k/{i}"] = np.array(list(values), dtype=str)
        mine[f"v/{i}"] = np.array([values[k] for k in values], dtype=float)
        mine.update({f"a/{i}/{j}": a for j, a in enumerate(arrays)})
    every = {k: v for part in processes.allgather(mine) for k, v in part.items()}
    out = []
    for i in range(len(items)):
        keys, vals = every[f"k/{i}"], every[f"v/{i}"]
        values = {str(k): float(v) for k, v in zip(keys, vals, strict=True)}
        out.append((values, [every[f"a/{i}/{j}"] for j in range(int(every[f"n/{i}"]))]))
    return out
