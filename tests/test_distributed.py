"""jaxcart grid across processes (jax.distributed): two processes on localhost on the CPU,
each computing its share of the blocks, give exactly the single-process grid."""

import os
import socket
import subprocess
import sys

import jax.numpy as jnp
import numpy as np

import jaxcart as jc
from tuning.design import grid

RANGES = {"kp": (40.0, 120.0, 5), "kd": (3.0, 9.0, 4), "ki": (0.0, 2.0, 3)}  # 60 points
BLOCK = 16  # 4 blocks: process 0 computes blocks 0 and 2, process 1 blocks 1 and 3 (short)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_equal_one(tmp_path):
    port = _free_port()
    argv = [sys.executable, "-m", "tuning", "--no-cache", "grid", "--horizon", "1.5"]
    for name, (lo, hi, n) in RANGES.items():
        argv += [f"--{name}", f"{lo:g}:{hi:g}:{n}"]
    argv += ["--block", str(BLOCK), "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2"]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    procs = []
    for i in range(2):
        folder = tmp_path / f"p{i}"
        folder.mkdir()
        procs.append(
            subprocess.Popen(
                [*argv, "--process-id", str(i), "--out", "g.npz", "--json", "g.json"],
                cwd=folder,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )
    # Meanwhile the same grid in this process, blocks of the same size (the same programs).
    axes = [grid.gain_axis(*r) for r in RANGES.values()]
    ref = grid.grid_search(
        jc.handout_plant(),
        jc.PID(v_limit=6.0),
        jc.step(0.5, horizon=1.5),
        *axes,
        dtype=jnp.float32,
        block=BLOCK,
    )
    outs = [p.communicate(timeout=120) for p in procs]
    for p, (_out, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-2000:]
    assert "sent to process 0" in outs[1][0]
    assert "in process 1 of 2" in outs[1][1] and "28/28 points" in outs[1][1]  # 16 + 12
    assert not (tmp_path / "p1" / "g.npz").exists()  # only process 0 writes the outputs
    assert "in process 0 of 2" in outs[0][1] and "feasible:" in outs[0][0]
    with np.load(tmp_path / "p0" / "g.npz") as data:
        for name in jc.StepInfo._fields:
            np.testing.assert_array_equal(data[name], getattr(ref.info, name), name)
        np.testing.assert_array_equal(data["feasible"], ref.feasible)
        assert tuple(data["best_index"]) == ref.best_index
    assert not (tmp_path / "p0" / "grid-blocks").exists()  # removed once the outputs exist
