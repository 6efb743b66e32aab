"""Programs kept on disk (jaxcart.aot): a later process loads the traced program instead of
tracing, with results identical to plain jax.jit; anything wrong falls back to jit."""

import os
import subprocess
import sys
from collections import namedtuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcart import aot
from jaxcart.cache import enable_persistent_cache

Pair = namedtuple("Pair", "a b")


def _loop(x, pair, scale):
    """A small scan, so the program has a loop like the real ones."""

    def body(c, k):
        c = c * pair.a + scale * jnp.sin(c + k)
        return c, c

    c, trace = jax.lax.scan(body, x, jnp.arange(20.0))
    return Pair(c, trace.sum(axis=0) + pair.b)


@pytest.fixture
def programs(tmp_path, monkeypatch):
    monkeypatch.delenv("JAXCART_NO_CACHE", raising=False)
    before = jax.config.jax_compilation_cache_dir
    enable_persistent_cache(tmp_path / "xla")
    yield tmp_path / "programs"
    jax.config.update("jax_compilation_cache_dir", before)


def _args():
    return jnp.linspace(0.0, 1.0, 4), Pair(jnp.asarray(0.9), np.arange(4.0)), 0.25


def test_saved_program_is_loaded_and_agrees_with_jit(programs):
    first = aot.jit(_loop, "test-loop", static=("v", 1))
    out = first(*_args())
    assert first.sources == ["export"]
    assert len(list(programs.glob("test-loop-*.bin"))) == 1
    again = aot.jit(_loop, "test-loop", static=("v", 1))
    out2 = again(*_args())
    assert again.sources == ["disk"]
    ref = jax.jit(_loop)(*_args())
    for x, y, z in zip(out, out2, ref, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(z))
        np.testing.assert_array_equal(np.asarray(y), np.asarray(z))
    assert isinstance(out2, Pair)
    # Other static settings or shapes are other programs; the same call reuses its entry.
    other = aot.jit(_loop, "test-loop", static=("v", 2))
    other(*_args())
    assert other.sources == ["export"]
    again(jnp.zeros(3), Pair(jnp.asarray(0.5), np.zeros(3)), 1.0)
    again(*_args())
    assert again.sources == ["disk", "export"]
    assert again.cache_size() == 2


def test_damaged_file_is_replaced(programs):
    aot.jit(_loop, "test-bad")(*_args())
    (path,) = programs.glob("test-bad-*.bin")
    path.write_bytes(b"not a program")
    fresh = aot.jit(_loop, "test-bad")
    out = fresh(*_args())
    assert fresh.sources == ["export"]
    np.testing.assert_array_equal(np.asarray(out.a), np.asarray(jax.jit(_loop)(*_args()).a))
    assert path.read_bytes() != b"not a program"


def test_off_without_the_cache(programs, monkeypatch):
    monkeypatch.setenv("JAXCART_NO_CACHE", "1")
    prog = aot.jit(_loop, "test-off")
    prog(*_args())
    assert prog.sources == ["jit"]
    assert not list(programs.glob("test-off-*"))


SCRIPT = """
import sys
from jaxcart.cache import enable_persistent_cache
enable_persistent_cache(sys.argv[1])
import jax
jax.config.update("jax_enable_x64", True)
from jaxcart import aot
sys.path.insert(0, sys.argv[2])
from test_aot import _loop, _args
prog = aot.jit(_loop, "test-process", static=("v", 1))
out = prog(*_args())
print(prog.sources[0], repr(float(out.a.sum())))
"""


def test_a_new_process_finds_the_program(tmp_path):
    """The file name is the same in every process (no object ids or per-process state)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX", "XDG_CACHE"))}
    env["JAXCART_NO_CACHE"] = "0"
    here = os.path.dirname(__file__)
    runs = [
        subprocess.run(
            [sys.executable, "-c", SCRIPT, str(tmp_path / "xla"), here],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        for _ in range(2)
    ]
    for r in runs:
        assert r.returncode == 0, r.stderr
    (src1, value1), (src2, value2) = (r.stdout.split() for r in runs)
    assert (src1, src2) == ("export", "disk")
    assert value1 == value2


def test_a_file_others_may_write_is_not_loaded(programs):
    """Programs are unpickled: only files of this user that nobody else can write are read."""
    if not hasattr(os, "getuid"):
        pytest.skip("POSIX permissions")
    aot.jit(_loop, "test-perm")(*_args())
    (path,) = programs.glob("test-perm-*.bin")
    path.chmod(0o666)
    fresh = aot.jit(_loop, "test-perm")
    fresh(*_args())
    assert fresh.sources == ["export"]
    assert path.stat().st_mode & 0o022 == 0  # replaced by a file of our own


def test_inside_a_transformation_it_nests_like_jit(programs):
    prog = aot.jit(lambda x: jnp.sin(x) * 2.0, "test-nest")
    out = jax.vmap(prog)(jnp.arange(3.0))
    np.testing.assert_allclose(np.asarray(out), 2.0 * np.sin(np.arange(3.0)), rtol=1e-15)
    assert prog.sources == []


def test_the_folder_keeps_the_newest_programs(tmp_path):
    """Every edit of the source files new programs: the oldest beyond the cap are removed."""
    for i in range(6):
        f = tmp_path / f"p{i}.bin"
        f.write_bytes(b"x")
        os.utime(f, (1000.0 + i, 1000.0 + i))
    (tmp_path / "other.txt").write_text("not a program")
    assert aot.prune(tmp_path, keep=4) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "other.txt",
        "p2.bin",
        "p3.bin",
        "p4.bin",
        "p5.bin",
    ]
    assert aot.prune(tmp_path, keep=4) == 0
