"""The persistent compilation cache: on by default in the user's cache folder, off on request,
capped at jaxcart.cache.MAX_BYTES by removing the least recently used programs (and nothing
else). Every folder here is the test's own (tests/conftest.py also gives each test process its
own XDG_CACHE_HOME): the user's cache is never touched."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from jaxcart import cache

ROOT = Path(__file__).resolve().parents[1]
#: Sizes here are small multiples of this (real files, no sparse-file trick), the caps scaled.
KB = 1 << 10


def _entry(folder: Path, name: str, size: int, age_s: float, *, read_age_s=None) -> Path:
    """A JAX cache entry of ``size`` bytes written ``age_s`` seconds ago and last read
    ``read_age_s`` seconds ago (default: when written)."""
    path = folder / f"{name}-cache"
    path.write_bytes(b"\0" * size)
    now = time.time()
    written = now - age_s
    read = now - (age_s if read_age_s is None else read_age_s)
    os.utime(path, (read, written))
    return path


def _simulate(home: Path, *flags: str, **extra: str) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX", "XDG_CACHE"))}
    env["HOME"] = str(home)
    env.update(extra)
    code = "import sys; from tuning.commands.main import main; sys.exit(main(sys.argv[1:]))"
    # --smooth: the jitted simulator, whose program is what the cache keeps.
    args = [*flags, "simulate", "--smooth", "--horizon", "0.2", "--out", str(home / "run.csv")]
    done = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr


def test_compiled_programs_are_kept_in_the_users_cache_folder(tmp_path):
    # A full folder from earlier runs: a command that turns the cache on brings it under the
    # cap (the oldest program goes), and leaves what is not a program alone. The cap, set by
    # the environment here, is 100 kB.
    folder = tmp_path / ".cache" / "jaxcart" / "xla"
    folder.mkdir(parents=True)
    old = _entry(folder, "jit_old-0", 60 * KB, age_s=3600)
    recent = _entry(folder, "jit_recent-0", 60 * KB, age_s=60)
    (folder / "notes.txt").write_text("mine")
    _simulate(tmp_path, **{cache.MAX_BYTES_VARIABLE: str(100 * KB)})
    kept = list(folder.iterdir())
    assert any(p.name.startswith("jit_simulate") for p in kept)
    assert not old.exists() and recent.exists() and (folder / "notes.txt").exists()


def test_prune_removes_the_least_recently_used_programs_beyond_the_cap(tmp_path):
    folder = tmp_path / "xla"
    folder.mkdir()
    a = _entry(folder, "jit_a-1", 40 * KB, age_s=400)  # written first, never read again
    b = _entry(folder, "jit_b-2", 40 * KB, age_s=500, read_age_s=10)  # older, read lately
    c = _entry(folder, "jit_c-3", 40 * KB, age_s=300)
    d = _entry(folder, "jit_d-4", 40 * KB, age_s=200)
    (folder / "jit_a-1-atime").write_bytes(b"12345678")  # JAX's LRU companion goes with it
    # Never touched: files that are not JAX entries, subfolders, links (and their targets).
    outside = tmp_path / "precious-cache"
    outside.write_bytes(b"x" * 1000)
    (folder / "link-cache").symlink_to(outside)
    (folder / "sub").mkdir()
    deep = _entry(folder / "sub", "jit_deep-5", 40 * KB, age_s=1000)
    other = folder / "README"
    other.write_text("x" * 1000)
    os.utime(other, (0, 0))

    assert cache.prune(folder, max_bytes=200 * KB) == 0  # 160 kB: under the cap
    assert cache.prune(folder, max_bytes=100 * KB) == 2  # 160 -> 80 kB: a, then c
    assert not a.exists() and not (folder / "jit_a-1-atime").exists() and not c.exists()
    assert b.exists() and d.exists()
    assert outside.exists() and (folder / "link-cache").is_symlink() and deep.exists()
    assert other.exists()
    assert cache.prune(folder, max_bytes=0) == 2  # everything of JAX's, nothing else
    assert sorted(p.name for p in folder.iterdir()) == ["README", "link-cache", "sub"]
    assert cache.prune(tmp_path / "absent") == 0
    with pytest.raises(ValueError, match="max_bytes"):
        cache.prune(folder, max_bytes=-1)


def test_turning_the_cache_on_prunes_its_own_folder_only(tmp_path, monkeypatch):
    """enable_persistent_cache brings jaxcart's own folder under the cap (here without telling
    the test process's JAX to use it), and leaves a folder it is given alone."""
    import jax

    monkeypatch.setattr(cache, "ENABLED", cache.ENABLED)
    monkeypatch.setattr(jax.config, "update", lambda *args: None)
    monkeypatch.delenv("JAXCART_NO_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home"))
    monkeypatch.setenv(cache.MAX_BYTES_VARIABLE, str(100 * KB))
    own, given = cache.cache_dir(), tmp_path / "shared-jax-cache"
    for folder in (own, given):
        folder.mkdir(parents=True)
        _entry(folder, "jit_old-0", 60 * KB, age_s=3600)
        _entry(folder, "jit_new-0", 60 * KB, age_s=60)
    assert cache.enable_persistent_cache() == own
    assert sorted(p.name for p in own.iterdir()) == ["jit_new-0-cache"]
    assert cache.enable_persistent_cache(given) == given
    assert len(list(given.iterdir())) == 2


def test_the_cap_from_the_environment(monkeypatch, capsys):
    monkeypatch.delenv(cache.MAX_BYTES_VARIABLE, raising=False)
    assert cache.max_bytes() == cache.MAX_BYTES
    monkeypatch.setenv(cache.MAX_BYTES_VARIABLE, "12345")
    assert cache.max_bytes() == 12345
    monkeypatch.setenv(cache.MAX_BYTES_VARIABLE, "1 GB")
    assert cache.max_bytes() == cache.MAX_BYTES
    assert "JAXCART_CACHE_MAX_BYTES='1 GB' is not a whole number" in capsys.readouterr().err


def test_no_cache_keeps_nothing(tmp_path):
    _simulate(tmp_path, "--no-cache")
    assert not (tmp_path / ".cache" / "jaxcart").exists()
