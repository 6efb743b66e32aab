"""Helper processes for the Python-bound work of a fit: many independent exact-simulator runs.

The exact simulator (:mod:`jaxcart.exact`) is plain Python, a few microseconds a sample, and a
diagnosis makes a couple of thousand of its runs: the forward differences of each exact
Gauss-Newton step, each recording of a trial. They are independent, so :meth:`Helpers.map`
spreads them over helper processes while the calling process takes its own share: on a 2-core
machine one helper and the caller run two at a time.

The caller owns the helpers, as :mod:`concurrent.futures` and scipy's ``workers=`` have it: a
command creates them (``with Helpers() as helpers:``), hands them to the fits that make exact
runs (``fit(..., executor=helpers)``, ``diagnose(..., executor=helpers)``) and closes them on
its way out, so that no process outlives the command. A library call given no executor makes
its runs in the calling process (:data:`SERIAL`); the library never starts a process on its
own, and no environment variable chooses for it.

The helpers are started with :mod:`subprocess` (``python -m jaxcart.workers``), never with
:mod:`multiprocessing`: a spawned ``multiprocessing`` worker re-imports the caller's
``__main__``, which hangs a user's script that calls a fit without an ``if __name__ ==
"__main__"`` guard, and a forked one inherits JAX's threads. A helper runs module-level
functions on pickled arguments, ignores Ctrl-C (the caller decides) and exits when the caller
closes its pipe or exits. A helper that fails or dies only loses speed: its item is computed
again by the caller, whose exception, if any, is the one raised. Results are the same, float
for float, as the caller's own (the same code on the same inputs).
"""

from __future__ import annotations

import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
from collections.abc import Callable, Iterable

#: Most helpers started by default.
MOST = 7
_HEADER = struct.Struct("!Q")


def default_count() -> int:
    """Helpers a command starts unless told otherwise: one fewer than the cores this process may
    use, at most :data:`MOST`; none where the pipes cannot be waited on (not POSIX)."""
    if os.name != "posix":
        return 0  # (the helpers' pipes are waited on with select: POSIX only)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return min(max((cores or 1) - 1, 0), MOST)


class Serial:
    """Every item in the calling process, in order: the executor of a call given none."""

    def map(self, fn: Callable, items: Iterable, weights: Iterable[float] | None = None) -> list:
        """``[fn(x) for x in items]`` (``weights`` are ignored)."""
        return [fn(x) for x in items]


#: The executor of a library call given none.
SERIAL = Serial()


class Helpers:
    """``count`` helper processes (default :func:`default_count`; 0: everything runs in the
    calling process) that share out :meth:`map`'s items with it.

    Created by the command that needs them and closed by it (a context manager): started on
    entering (so that they have imported by the time the first map needs them: a fit's smooth
    part runs meanwhile), stopped on leaving. One map at a time: a second thread's map waits
    for the first to return (the lab's diagnosis and its parts share one set of helpers)."""

    def __init__(self, count: int | None = None):
        self.count = default_count() if count is None else max(int(count), 0)
        self._lock = threading.Lock()
        self._procs: list[_Helper] = []
        self._closed = False
        #: (module, name) of functions a helper could not import: computed here from then on.
        self._unknown: set = set()

    def __enter__(self) -> Helpers:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        """Start the helpers now (they import while the caller works on)."""
        with self._lock:
            self._started()

    def _started(self) -> list[_Helper]:
        """The helpers still alive, started first where none were (the lock held); none
        once closed (a map then runs here)."""
        if not self._procs and self.count and not self._closed:
            self._procs = [_Helper() for _ in range(self.count)]
        return [h for h in self._procs if h.alive]

    def map(self, fn: Callable, items: Iterable, weights: Iterable[float] | None = None) -> list:
        """``[fn(x) for x in items]``, the items shared between the helpers and this process.

        ``fn``: a module-level function (pickled by name); the items and results must pickle.
        ``weights``: each item's cost (an exact run's number of samples, say; equal by
        default), by which the items are dealt out so that every process has about the same
        work. The order of the results is the order of the items."""
        items = list(items)
        name = (getattr(fn, "__module__", None), getattr(fn, "__qualname__", None))
        if len(items) < 2 or self.count == 0 or name in self._unknown:
            return [fn(x) for x in items]
        with self._lock:  # (another thread's map: this one waits its turn)
            helpers = [h for h in self._started() if h.is_ready()]
            weights = [1.0] * len(items) if weights is None else [float(w) for w in weights]
            return self._spread(fn, name, items, helpers, weights)

    def _spread(self, fn, name, items, helpers, weights) -> list:
        """Each helper gets its share in one message; this process computes its own
        meanwhile."""
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
                self._unknown.add(name)
            if ok is not True:  # computed here: its exception, if any, is raised here
                values = [fn(items[i]) for i in share]
            for i, v in zip(share, values, strict=True):
                results[i] = v
        return results

    def close(self) -> None:
        """Stop the helpers (each reads the end of its input and exits; waited for). A map
        after this runs in the calling process."""
        with self._lock:
            for h in self._procs:
                h.close()
            self._procs, self._closed = [], True


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


class _Helper:
    """One helper process and its pipes. ``ready``: it has imported and waits for work."""

    def __init__(self):
        # float64 on: a float64 JAX array in an item (a plant's parameter) arrives as one.
        env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_ENABLE_X64="1")
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
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller decides when to stop
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # a print in a task must not corrupt the pipe
    # Imported before saying ready, so that the first task starts at once: the helper's own
    # start-up (a caller that never makes an exact run never imports the simulator for it).
    # lazy: jaxcart.exact imports jax, 0.3-0.5 s at start-up (python -X importtime), and the
    # command line's parser imports this module
    import jaxcart.exact  # noqa: F401

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
