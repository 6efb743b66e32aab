"""Processes of one jax.distributed run on localhost, for the tests of the commands that run
across processes (each process holds two CPU devices, as the test process does: conftest)."""

import os
import socket
import subprocess
import sys


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def spawn(tmp_path, argv, n: int = 2, env: dict | None = None):
    """``n`` processes of ``jaxcart ARGV`` (no caches), each in its own folder p0/ p1/ ...,
    process ids from the environment variable (not the option)."""
    port = free_port()
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
        **(env or {}),
    }
    procs = []
    for i in range(n):
        folder = tmp_path / f"p{i}"
        folder.mkdir()
        cluster = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n)]
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "tuning", "--no-cache", *argv, *cluster],
                cwd=folder,
                env={**env, "JAXCART_PROCESS_ID": str(i)},
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )
    return procs
