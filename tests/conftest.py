"""Strict JAX for every test: float64, rank promotion raises, two CPU devices for the sharded
path; every figure written is checked (tests/figcheck.py), and closed after each test."""

import atexit
import os
import shutil
import tempfile

# Two CPU devices so the sharded batch path runs in CI (set before jax starts).
os.environ.setdefault("MPLBACKEND", "Agg")
# Commands run in-process turn jaxcart's caches on: give each test process a cache folder of
# its own, so that two test processes (pytest -n 2) never write one file at once and the
# user's own cache is left alone.
_CACHE = tempfile.mkdtemp(prefix="jaxcart-test-cache-")
os.environ["XDG_CACHE_HOME"] = _CACHE
atexit.register(shutil.rmtree, _CACHE, True)

# Before JAX starts: jaxcart's XLA setting (loops compiled whole, jaxcart.xlaflags), as every
# command asks for it, so the tests run what the commands run.
from jaxcart import xlaflags  # noqa: E402

xlaflags.request()

# isort: split
import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_num_cpu_devices", 2)
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

REALDATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "realdata")


@pytest.fixture
def realdata():
    """Path of ../shared/realdata (the lab's real recordings); skips when absent."""
    path = os.path.abspath(REALDATA)
    if not os.path.isdir(path):
        pytest.skip("../shared/realdata is not beside this checkout")
    return path


def _checked_savefig():
    """Every figure a test writes is checked as written (tests/figcheck.py): nothing cut off
    at the canvas's edges, no legend entry twice."""
    from figcheck import figure_problems
    from matplotlib.figure import Figure

    savefig = Figure.savefig
    if getattr(savefig, "checked", False):
        return

    def checked(self, *args, **kwargs):
        out = savefig(self, *args, **kwargs)
        problems = figure_problems(self)
        assert not problems, "the figure written is wrong:\n" + "\n".join(problems)
        return out

    checked.checked = True
    Figure.savefig = checked


_checked_savefig()


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")
