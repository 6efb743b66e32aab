"""The persistent compilation cache: on by default in the user's cache folder, off on request."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _simulate(home: Path, *flags: str) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX", "XDG_CACHE"))}
    env["HOME"] = str(home)
    code = "import sys; from tuning.cli import main; sys.exit(main(sys.argv[1:]))"
    args = [*flags, "simulate", "--horizon", "0.2", "--out", str(home / "run.csv")]
    done = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr


def test_compiled_programs_are_kept_in_the_users_cache_folder(tmp_path):
    _simulate(tmp_path)
    kept = list((tmp_path / ".cache" / "jaxcart" / "xla").iterdir())
    assert any(p.name.startswith("jit_simulate") for p in kept)


def test_no_cache_keeps_nothing(tmp_path):
    _simulate(tmp_path, "--no-cache")
    assert not (tmp_path / ".cache" / "jaxcart").exists()
