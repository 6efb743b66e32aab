"""One function run in a daemon thread, its result (or exception) collected later.

Used where two long, independent pieces of work can overlap (the lab's joint diagnosis beside
its parts: one compiles while the other fits; the PID's re-tune beside Part (v)) and by
:mod:`tuning.commands.interruptible`. Whoever starts one collects its result (:meth:`result`)
before it builds anything that holds it: a result object is plain data, never a handle on a
running thread. The thread is a daemon: a process that ends (an error elsewhere, Ctrl-C) does
not wait for it. A thread does not inherit its starter's ``jax.enable_x64`` scope: the work
run in one sets its own precision.
"""

from __future__ import annotations

import threading
import weakref

#: Every Background not yet collected (:func:`running` looks for those still at work).
_ALL: weakref.WeakSet = weakref.WeakSet()


def running() -> list[str]:
    """The names of the background threads still at work (work a failed command abandons:
    inside XLA, such a thread aborts the interpreter's shutdown, so that the process's own
    command line ends without one, :func:`tuning.commands.main.main`)."""
    return [b._thread.name for b in list(_ALL) if b.alive()]


class Background:
    """``func(*args, **kwargs)`` started at once in a daemon thread named ``name``."""

    def __init__(self, func, *args, name: str = "jaxcart-background", **kwargs):
        self._box: dict = {}
        _ALL.add(self)

        def work():
            try:
                self._box["result"] = func(*args, **kwargs)
            except BaseException as exc:  # handed to the caller of result() as it is
                self._box["error"] = exc

        self._thread = threading.Thread(target=work, name=name, daemon=True)
        self._thread.start()

    def alive(self) -> bool:
        return self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def result(self):
        """The function's result once it has returned (waiting for it), or its exception
        re-raised here."""
        self._thread.join()
        if "error" in self._box:
            raise self._box["error"]
        return self._box.get("result")
