"""jaxcart's one XLA setting (jaxcart.xlaflags): loops compiled whole on a CPU. The flag string
it builds, that a request (the command line's) puts it in place before JAX starts (and leaves a
user's own value, or a backend that started first, alone) while importing jaxcart asks for
nothing, that XLA then compiles a chunk's loop into one kernel, and the chunk sizes the batches
choose from it."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import pytest

from jaxcart import xlaflags

OPTION = xlaflags.OPTION
EXTRA = "--xla_backend_extra_options="
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.parametrize(
    "flags, want",
    [
        ("", f"{EXTRA}{OPTION}=1048576"),
        ("--xla_dump_to=/tmp/d", f"--xla_dump_to=/tmp/d {EXTRA}{OPTION}=1048576"),
        # An existing map option is extended, not shadowed by a second one.
        (f"{EXTRA}a=1 --b", f"{EXTRA}a=1,{OPTION}=1048576 --b"),
        # The user's own value is kept.
        (f"{EXTRA}{OPTION}=1024", f"{EXTRA}{OPTION}=1024"),
        (f"{EXTRA}a=1,{OPTION}=5", f"{EXTRA}a=1,{OPTION}=5"),
        # An empty map option takes it; of two, the last does (XLA merges them).
        (f"--a {EXTRA} --b", f"--a {EXTRA}{OPTION}=1048576 --b"),
        (f"{EXTRA}a=1 {EXTRA}b=2", f"{EXTRA}a=1 {EXTRA}b=2,{OPTION}=1048576"),
    ],
)
def test_with_option_adds_merges_or_keeps(flags, want):
    assert xlaflags.with_option(flags, 1 << 20) == want
    assert xlaflags.threshold_in(want) == int(want.rsplit("=", 1)[1].split()[0])


def test_threshold_in_reads_the_last_value_and_nothing_else():
    assert xlaflags.threshold_in("") is None
    assert xlaflags.threshold_in(EXTRA) is None
    assert xlaflags.threshold_in(f"--x_{OPTION}=3") is None  # another flag's name
    assert xlaflags.threshold_in(f"{EXTRA}{OPTION}=2,{OPTION}=7") == 7
    assert xlaflags.threshold_in(f"{EXTRA}{OPTION}=2 {EXTRA}a=1") == 2  # merged maps


def _run(code: str, flags: str | None, **extra) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", xlaflags.OFF)}
    if flags is not None:
        env["XLA_FLAGS"] = flags
    env.update(extra)
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True, text=True, timeout=120, cwd=ROOT, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


_PROBE = """
    import os
    {first}
    import jax, jax.numpy as jnp
    from jaxcart import xlaflags
    from jaxcart.batch_metrics import default_chunk
    f = jax.jit(lambda x: jax.lax.scan(lambda c, _: (c * 1.01 + 1.0, None), x, None, 100)[0])
    text = f.lower(jnp.ones(256)).compile().as_text()
    print(xlaflags.loop_kernels(), "xla_cpu_small_call" in text, default_chunk(),
          os.environ.get("XLA_FLAGS", "").replace(" ", "|") or "-")
"""


#: What the command line does before JAX starts (tuning/commands/main.py).
REQUEST = "import jaxcart.xlaflags; jaxcart.xlaflags.request()"


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="a CPU backend's option")
def test_a_request_before_jax_starts_compiles_a_chunks_loop_whole():
    kernels, whole, chunk, flags = _run(_PROBE.format(first=REQUEST), None)
    assert (kernels, whole, int(chunk)) == ("True", "True", 256)
    assert flags == f"--xla_backend_extra_options={OPTION}=1048576"


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="a CPU backend's option")
def test_importing_jaxcart_asks_for_nothing():
    kernels, whole, chunk, flags = _run(_PROBE.format(first="import jaxcart"), None)
    assert (kernels, whole, int(chunk), flags) == ("False", "False", 4096, "-")


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="a CPU backend's option")
def test_a_users_smaller_value_is_kept_and_the_chunks_stay_wide():
    mine = f"--xla_backend_extra_options={OPTION}=1024"
    kernels, whole, chunk, flags = _run(_PROBE.format(first=REQUEST), mine)
    assert (kernels, whole, int(chunk), flags) == ("False", "False", 4096, mine)


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="a CPU backend's option")
def test_turned_off_it_leaves_xla_flags_alone():
    kernels, whole, chunk, flags = _run(_PROBE.format(first=REQUEST), None, **{xlaflags.OFF: "0"})
    assert (kernels, whole, int(chunk), flags) == ("False", "False", 4096, "-")


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="a CPU backend's option")
def test_a_backend_started_first_is_left_alone():
    first = "import jax.numpy; jax.numpy.ones(2).block_until_ready(); " + REQUEST
    kernels, whole, chunk, flags = _run(_PROBE.format(first=first), None)
    assert (kernels, whole, int(chunk), flags) == ("False", "False", 4096, "-")


def test_the_suite_runs_with_loops_compiled_whole():
    """conftest asks for the setting before JAX starts: the tests run what the commands run."""
    if jax.default_backend() == "cpu":
        assert xlaflags.loop_kernels()
        f = jax.jit(lambda x: jax.lax.scan(lambda c, _: (c + 1.0, None), x, None, 10)[0])
        assert "xla_cpu_small_call" in f.lower(jnp.ones(8)).compile().as_text()


def test_on_another_backend_the_chunks_are_wide_and_no_cpu_option_is_passed(monkeypatch):
    """A GPU: the batches keep their wide chunks, and neither the forward batch nor the bench's
    gradient row asks for a CPU option (what a GPU run would compile, without a GPU here)."""
    import jaxcart.batch_metrics as batch
    from jaxcart import parallel
    from tuning.benchmark import workload as bench

    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert batch.default_chunk() == batch.WIDE_CHUNK
    assert batch.COMPILER_OPTIONS.get("gpu") is None
    seen = {}
    real = parallel.sharded_map

    def spy(fn, **kwargs):
        seen.update(kwargs)
        return real(fn, **kwargs)

    monkeypatch.setattr(bench, "sharded_map", spy)  # the name the benchmark calls
    bench.grad_evaluator(*bench.w1_problem(0.01), chunk=4)
    assert seen["compiler_options"] == {} and seen["whole_chunks"]
