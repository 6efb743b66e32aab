"""Helper processes for the Python-bound work of a fit: many independent exact-simulator runs.

The exact simulator (:mod:`jaxcart.exact`) is plain Python, a few microseconds a sample, and a
diagnosis makes a couple of thousand of its runs: the forward differences of each exact
Gauss-Newton step, each recording of a trial. They are independent, so :func:`map` spreads
them over helper processes while the calling process takes its own share: on a 2-core machine
one helper and the caller run two at a time.

The helpers are started with :mod:`subprocess` (``python -m jaxcart.workers``), never with
:mod:`multiprocessing`: a spawned ``multiprocessing`` worker re-imports the caller's
``__main__``, which hangs a user's script that calls a fit without an ``if __name__ ==
"__main__"`` guard, and a forked one inherits JAX's threads. A helper runs module-level
functions on pickled arguments, ignores Ctrl-C (the caller decides) and exits when the caller
closes its pipe or exits. A helper that fails or dies only loses speed: its item is computed
again by the caller, whose exception, if any, is the one raised. Results are the same, float
for float, as the caller's own (the same code on the same inputs).

``JAXCART_WORKERS=N`` sets the number of helpers (0: none); by default one fewer than the
cores this process may use, at most :data:`MOST`. Inside a helper there are none, nor in a
jax.distributed run (its processes share out the work themselves).
"""

from __future__ import annotations

import atexit
import os
import pickle
import select
import struct
import subprocess
import sys
import threading
from collections.abc import Callable, Iterable

#: The environment variable that sets the number of helpers.
VARIABLE = "JAXCART_WORKERS"
#: Set in a helper's environment: a helper starts none of its own.
INSIDE = "JAXCART_IN_WORKER"
#: Most helpers started by default.
MOST = 7
_HEADER = struct.Struct("!Q")

_lock = threading.Lock()
_pool: list[_Helper] | None = None
#: (module, name) of functions a helper could not import: computed here from then on.
_unknown: set = set()


def count() -> int:
    """How many helpers :func:`map` uses (0: everything runs in this process)."""
    if os.environ.get(INSIDE) or os.name != "posix" or _distributed():
        return 0  # (the helpers' pipes are waited on with select: POSIX only)
    given = os.environ.get(VARIABLE, "").strip()
    if given:
        try:
            return max(int(given), 0)
        except ValueError:
            from jaxcart.errors import UserError

            raise UserError(
                f"{VARIABLE}={given!r}: give a whole number of helper processes (0 for none)"
            ) from None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return min(max((cores or 1) - 1, 0), MOST)


def _distributed() -> bool:
    """A jax.distributed run (:func:`jaxcart.parallel.init_distributed`): its processes share
    out the work, several of them perhaps on one host, so none starts helpers."""
    dist = sys.modules.get("jax._src.distributed")
    return dist is not None and dist.global_state.client is not None


def start() -> None:
    """Start the helpers now, so that they have imported by the time :func:`map` needs them
    (a fit starts them before its compiled part; until then :func:`map` runs here)."""
    if count() and _lock.acquire(blocking=False):
        try:
            _helpers()
        finally:
            _lock.release()


def map(fn: Callable, items: Iterable, weights: Iterable[float] | None = None) -> list:  # noqa: A001
    """``[fn(x) for x in items]``, the items shared between the helpers and this process.

    ``fn``: a module-level function (pickled by name); the items and results must pickle.
    ``weights``: each item's cost (an exact run's number of samples, say; equal by default),
    by which the items are dealt out so that every process has about the same work. The order
    of the results is the order of the items."""
    items = list(items)
    name = (getattr(fn, "__module__", None), getattr(fn, "__qualname__", None))
    if len(items) < 2 or count() == 0 or name in _unknown:
        return [fn(x) for x in items]
    if not _lock.acquire(blocking=False):
        return [fn(x) for x in items]  # (another thread's map holds the helpers)
    try:
        helpers = [h for h in _helpers() if h.is_ready()]
        weights = [1.0] * len(items) if weights is None else [float(w) for w in weights]
        return _spread(fn, items, helpers, weights)
    finally:
        _lock.release()


def _spread(fn, items, helpers, weights) -> list:
    """Each helper gets its share in one message; this process computes its own meanwhile."""
    mine, *theirs = _deal(weights, len(helpers) + 1)
    sent = []
    for h, share in zip(helpers, theirs, strict=True):
        if share and h.send(fn, [items[i] for i in share]):
            sent.append((h, share))
        else:
            mine += share
    results: list = [None] * len(items)
    try:
        for i in mine:
            results[i] = fn(items[i])
    finally:  # every reply read, also when this share raised: none is left for the next map
        replies = [(share, *h.receive()) for h, share in sent]
    for share, ok, values in replies:
        if ok == "unknown":  # the helper cannot import fn (a script's own): none will
            _unknown.add((getattr(fn, "__module__", None), getattr(fn, "__qualname__", None)))
        if ok is not True:  # computed here: its exception, if any, is raised here
            values = [fn(items[i]) for i in share]
        for i, v in zip(share, values, strict=True):
            results[i] = v
    return results


def _deal(weights, n: int) -> list[list[int]]:
    """The item indices in ``n`` shares of about equal weight (the heaviest item first, each
    to the lightest share so far)."""
    shares: list[list[int]] = [[] for _ in range(n)]
    loads = [0.0] * n
    for i in sorted(range(len(weights)), key=lambda i: -weights[i]):
        k = loads.index(min(loads))
        shares[k].append(i)
        loads[k] += weights[i]
    return shares


def _helpers() -> list[_Helper]:
    global _pool
    if _pool is None or len(_pool) != count():
        shutdown()
        _pool = [_Helper() for _ in range(count())]
    _pool = [h for h in _pool if h.alive] or _pool
    return _pool


def shutdown() -> None:
    """Stop the helpers (they are started again when needed)."""
    global _pool
    for h in _pool or []:
        h.close()
    _pool = None


atexit.register(shutdown)


class _Helper:
    """One helper process and its pipes. ``ready``: it has imported and waits for work."""

    def __init__(self):
        # float64 on: a float64 JAX array in an item (a plant's parameter) arrives as one.
        env = dict(os.environ, **{INSIDE: "1", "JAX_PLATFORMS": "cpu", "JAX_ENABLE_X64": "1"})
        # The helper imports what this process imports (a test folder, an editable install).
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "jaxcart.workers"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=env,
        )
        self.fd = self.proc.stdout.fileno()
        self.ready = False
        self.alive = True

    def is_ready(self) -> bool:
        """Whether it waits for work (it has said so), without waiting for it."""
        if self.alive and not self.ready and select.select([self.fd], [], [], 0)[0]:
            self.receive()
        return self.ready

    def send(self, fn, items) -> bool:
        try:
            _write(self.proc.stdin, pickle.dumps((fn, items), protocol=pickle.HIGHEST_PROTOCOL))
            return True
        except (pickle.PicklingError, AttributeError, TypeError):
            return False  # not picklable: computed by the caller
        except OSError:
            self.alive = self.ready = False  # the helper has gone
            return False

    def receive(self):
        """(True, results) of the items sent; ("unknown", why) where it could not read them,
        (False, ...) where they failed, it said ready or it died."""
        try:
            ok, value = pickle.loads(_read(self.proc.stdout))
        except (OSError, EOFError, pickle.UnpicklingError, struct.error):
            self.alive = self.ready = False
            return False, None
        if ok == "ready":
            self.ready = True
            return False, None
        return ok, value

    def close(self):
        self.alive = self.ready = False
        try:
            self.proc.stdin.close()  # the helper reads the end of its input and exits
            self.proc.wait(timeout=2)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()


def _write(stream, body: bytes) -> None:
    stream.write(_HEADER.pack(len(body)) + body)
    stream.flush()


def _read(stream) -> bytes:
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise EOFError("the helper closed its pipe")
    (n,) = _HEADER.unpack(head)
    body = stream.read(n)
    if len(body) < n:
        raise EOFError("the helper closed its pipe")
    return body


def serve() -> None:
    """A helper's loop: read (function, items), write (True, results) or (False, why)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller decides when to stop
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # a print in a task must not corrupt the pipe
    import jaxcart.exact  # noqa: F401 - imported before saying ready: the first task starts at once

    _write(stdout, pickle.dumps(("ready", None)))
    while True:
        try:
            body = _read(stdin)
        except EOFError:
            return
        try:
            fn, items = pickle.loads(body)
        except Exception as exc:  # (AttributeError: a function of the caller's __main__)
            _write(stdout, pickle.dumps(("unknown", repr(exc))))
            continue
        try:
            out = pickle.dumps((True, [fn(x) for x in items]), pickle.HIGHEST_PROTOCOL)
        except Exception as exc:  # the caller computes the items itself and raises there
            out = pickle.dumps((False, repr(exc)))
        _write(stdout, out)


if __name__ == "__main__":
    serve()
