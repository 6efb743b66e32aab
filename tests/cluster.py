"""Processes of one jax.distributed run on localhost, for the tests of the commands that run
across processes (each process holds two CPU devices, as the test process does: conftest);
and processes simulated as threads of the test process over an in-memory key-value store, for
the exchange itself (no runtime)."""

import os
import socket
import subprocess
import sys
import threading

from jaxcart import parallel
from tuning.distributed import Exchange

#: The command line of ``python -m tuning``, run after a test's own code (``spawn(inject=)``).
MAIN = "import sys\nfrom tuning.commands.main import main\nsys.exit(main())\n"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def spawn(tmp_path, argv, n: int = 2, env: dict | None = None, inject: str | None = None):
    """``n`` processes of ``jaxcart ARGV`` (no caches), each in its own folder p0/ p1/ ...
    (made here unless the test put files in it), process ids from the environment variable
    (not the option). inject: Python code each process runs first (e.g. a failure patched
    in where ``JAXCART_PROCESS_ID`` is 1)."""
    port = free_port()
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
        **(env or {}),
    }
    run = ["-m", "tuning"] if inject is None else ["-c", inject + "\n" + MAIN]
    procs = []
    for i in range(n):
        folder = tmp_path / f"p{i}"
        folder.mkdir(exist_ok=True)
        cluster = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n)]
        procs.append(
            subprocess.Popen(
                [sys.executable, *run, "--no-cache", *argv, *cluster],
                cwd=folder,
                env={**env, "JAXCART_PROCESS_ID": str(i)},
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )
    return procs


class Store:
    """The runtime's key-value store and barrier in memory, shared by threads; a wait ends
    after ``wait_s`` [s] (a test that would hang fails instead)."""

    def __init__(self, count: int, wait_s: float = 20.0):
        self.data: dict = {}
        self.changed = threading.Condition()
        self.done = threading.Barrier(count)
        self.wait_s = wait_s

    def publish(self, key, data):
        with self.changed:
            self.data[key] = data
            self.changed.notify_all()

    def fetch(self, key, timeout_s=3600.0, *, delete=True):
        with self.changed:
            if not self.changed.wait_for(lambda: key in self.data, min(timeout_s, self.wait_s)):
                raise TimeoutError(f"{key} never published")
            return self.data.pop(key) if delete else self.data[key]

    def barrier(self, name, timeout_s=3600.0):
        self.done.wait(min(timeout_s, self.wait_s))


def in_threads(monkeypatch, work, count: int = 2, exchange=Exchange):
    """``work(exchange)`` in ``count`` threads, each one process of a run with its own
    ``exchange(index, count)`` over one :class:`Store`: [result or exception] by process."""
    store = Store(count)
    for name in ("publish", "fetch", "barrier"):
        monkeypatch.setattr(parallel, name, getattr(store, name))
    exchanges = [exchange(i, count) for i in range(count)]
    for ex in exchanges:  # one run: each real process counts its own exchanges alike
        ex.run = exchanges[0].run
    out: list = [None] * count

    def run(i):
        try:
            out[i] = work(exchanges[i])
        except Exception as exc:
            out[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(count)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(3 * store.wait_s)
    assert not any(t.is_alive() for t in threads), "a process still waits"
    return out
