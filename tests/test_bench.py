"""The W1 benchmark: its four implementations compute the same loop, and its output is usable.

One tiny run (0.3 s horizon, a few hundred runs, one run per slow peer) is shared by the tests.
No rate is asserted beyond being positive: timings are not tests.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart
from jaxcart import parallel
from tuning.benchmark import ckernel, peers
from tuning.benchmark import workload as bench
from tuning.commands.main import main

HORIZON = 0.3  # s: short runs keep the file fast; the loop and its checks are unchanged


@pytest.fixture(scope="module")
def result():
    return bench.run_bench(
        batch=256,
        slow_runs=1,
        numpy_runs=256,
        grad_runs=32,
        grid_points=4,
        repeats=1,
        check_runs=4,
        progress=None,
        _horizon=HORIZON,
    )


def test_schema(result):
    names = [row["name"] for row in result["rows"]]
    assert names == [
        "jaxcart",
        "jaxcart-float64",
        "c-kernel",
        "python-control",
        "scipy",
        "numpy-vectorized",
    ]
    for row in result["rows"]:
        if "skipped" in row:  # only the C kernel, without a compiler
            assert row["name"] == "c-kernel" and ckernel.compiler() is None
            continue
        assert row["sims_per_s"] > 0 and np.isfinite(row["sims_per_s"])
        assert row["jaxcart_ratio"] > 0
    assert result["rows"][0]["jaxcart_ratio"] == 1.0
    jax32, jax64, c_row = result["rows"][:3]
    assert (jax32["dtype"], jax64["dtype"]) == ("float32", "float64")
    assert jax32["sims_per_cpu_s"] > 0 and jax64["sims_per_cpu_s"] > 0
    if "skipped" not in c_row:
        for row in (jax32, jax64):
            own = c_row["by_dtype"][row["dtype"]]["sims_per_cpu_s"]
            # Per CPU-second on a CPU; a GPU's wall rate against one C core elsewhere.
            ours = row["sims_per_cpu_s"] if jax.default_backend() == "cpu" else row["sims_per_s"]
            assert row["ceiling_ratio"] == pytest.approx(ours / own)
        assert c_row["threads"] == 1 and c_row["scalar_loop"]["sims_per_cpu_s"] > 0
        assert "c-kernel" in bench.format_table(result)
    assert result["grad_sims_per_s"] > 0 and result["grid_sims_per_s"] > 0
    grad = result["grad"]
    assert result["grad_ratio"] == {
        "sims_per_s": pytest.approx(grad["sims_per_s"] / jax32["sims_per_s"]),
        "sims_per_cpu_s": pytest.approx(grad["sims_per_cpu_s"] / jax32["sims_per_cpu_s"]),
    }
    assert len(grad["seconds"]) == len(grad["cpu_seconds"]) == 1  # repeats=1
    targets = result["targets"]
    assert targets["grad >= 1/4 of jaxcart sims/s"] == (result["grad_ratio"]["sims_per_s"] >= 0.25)
    for name, row in (("jaxcart", jax32), ("jaxcart-float64", jax64)):
        ok = targets[f"{name} >= 50 % of c-kernel per CPU-second"]
        assert ok is None if "skipped" in c_row else ok == (row["ceiling_ratio"] >= 0.5)
    assert "of jaxcart's sims/s" in bench.format_table(result)
    assert result["compile_s"] >= 0
    assert result["devices"] == len(parallel.devices())
    assert result["device_kind"] == parallel.devices()[0].device_kind
    assert result["backend"] == jax.default_backend()
    assert result["grid"]["runs"] == 4**3
    assert result["grad"]["all_finite"]
    assert set(result["ratios"]) == {*bench.PEERS, "jaxcart-float64"} | (
        set() if "skipped" in result["rows"][2] else {"c-kernel"}
    )
    assert "not the benchmark" in result["workload"]["name"]  # a short horizon says so
    assert result["workload"]["samples"] == 301
    json.dumps(bench.to_json(result), allow_nan=False)  # plain JSON, no Infinity


def test_peers_agree_with_jaxcart(result):
    """Four independent implementations of one loop: float64 positions within 1e-6 m of
    float64 jaxcart.simulate (measured ~1e-13 m), metrics identical to the sample."""
    for name in bench.PEERS:
        check = result["checks"][name]
        assert check["max_position_diff_m"] <= bench.TOLERANCE
        diff = check["max_metric_diff"]
        for key in ("rise_time", "settling_time", "saturation_time", "diverged"):
            assert diff[key] == 0.0, (name, key)
        assert diff["overshoot"] < 1e-8  # %
        assert diff["peak_voltage"] < 1e-9  # V
    assert result["max_peer_position_diff_m"] <= bench.TOLERANCE
    # jaxcart's streamed metrics against numpy on jaxcart's own trace: the same definitions.
    own = result["checks"]["jaxcart-metrics-vs-trace"]["max_metric_diff"]
    assert max(own.values()) < 1e-12


def test_float32_paths_agree(result):
    """numpy float32 against jaxcart float32 on 256 runs, and jaxcart float32 against float64:
    rounding only (1 sample of saturation time may flip; positions ~1e-6 m)."""
    for key in ("numpy-float32-vs-jaxcart-float32", "jaxcart-float32-vs-float64"):
        diff = result["checks"][key]["max_metric_diff"]
        assert diff["overshoot"] < 1e-3  # %
        assert diff["steady_state_error"] < 1e-5  # m
        assert diff["peak_voltage"] < 1e-3  # V
        assert diff["saturation_time"] <= 2e-3  # s
        assert diff["diverged"] == 0.0


def test_a_wrong_peer_is_caught():
    """The check is not vacuous: a plant 2 % off in B_eq fails it, loudly."""
    with jax.enable_x64(True):
        plant, controller, experiment = bench.w1_problem(HORIZON)
    gains = bench.w1_gains(2)
    reference = bench.reference_positions(plant, controller, experiment, gains)
    ref_metrics = bench.jaxcart_metrics(plant, controller, experiment, gains, jnp.float64)
    wrong = plant.replace(B_eq=5.5)
    info, trace = peers.numpy_batch(wrong, controller, experiment, gains, record=2)
    with pytest.raises(bench.PeerDisagreement, match="numpy-vectorized"):
        bench._check("numpy-vectorized", trace, reference, info, ref_metrics, bench.TOLERANCE)
    info, trace = peers.numpy_batch(plant, controller, experiment, gains, record=2)
    bench._check("numpy-vectorized", trace, reference, info, ref_metrics, bench.TOLERANCE)


@pytest.mark.parametrize("horizon, lo, hi", [(0.3, 0.1, 0.9), (0.05, 0.0, 0.1)])
def test_rise_time_of_a_run_that_never_reaches_90_percent(horizon, lo, hi):
    """A sluggish run (kp 10 V/m, kd 12 V s/m) reaches ~13 % in 0.3 s and < 10 % in 0.05 s:
    every implementation reports rise_time inf (not nan), and settling time inf, like jaxcart."""
    with jax.enable_x64(True):
        problem = bench.w1_problem(horizon)
    gains = np.array([[10.0, 12.0, 0.0]])
    ref = bench.jaxcart_metrics(*problem, gains, jnp.float64)
    y = bench.reference_positions(*problem, gains)[0]
    assert lo * bench.STEP <= y.max() < hi * bench.STEP  # the case this parameter covers
    numpy_info, _ = peers.numpy_batch(*problem, gains)
    _, scipy_info = peers.scipy_run(*problem, gains[0])
    for info in (ref, numpy_info, scipy_info):
        assert np.isinf(info["rise_time"]).all() and np.isinf(info["settling_time"]).all()
    assert max(bench._max_diff(numpy_info, ref).values()) < 1e-12


def test_zoh_against_python_control():
    """The peers' exact hold step equals python-control's c2d (zoh) of the same plant."""
    import control

    plant = jaxcart.handout_plant()
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    sys_d = control.ss([[0, 1], [0, -c / m]], [[0], [gamma / m]], [[1, 0]], [[0]]).sample(
        1e-3, method="zoh"
    )
    ad, bd = peers.zoh_matrices(plant, 1e-3)
    np.testing.assert_allclose(ad, sys_d.A, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(bd, sys_d.B[:, 0], rtol=1e-12, atol=1e-18)


def test_gradient_matches_finite_differences():
    """The benchmarked gradient (sharded vmap of grad) against central differences of the
    same loss, float64, 2 devices x 2 runs."""
    plant, controller, experiment = bench.w1_problem(HORIZON)
    gains = jnp.asarray(bench.w1_gains(2 * len(jax.devices())))
    evaluate = bench.grad_evaluator(plant, controller, experiment, chunk=2)
    loss, grad = evaluate(gains)
    f = jax.jit(lambda g: bench.smooth_loss(plant, controller, experiment, g))
    for i in range(gains.shape[0]):
        assert float(loss[i]) == pytest.approx(float(f(gains[i])), rel=1e-12)
        for j in range(3):
            h = 1e-5 * max(1.0, abs(float(gains[i, j])))
            step = jnp.zeros(3).at[j].set(h)
            fd = (f(gains[i] + step) - f(gains[i] - step)) / (2 * h)
            assert float(grad[i, j]) == pytest.approx(float(fd), rel=1e-5, abs=1e-9)


def test_batch_compiler_options_change_no_metric(monkeypatch):
    """The batch XLA options (jaxcart.batch_metrics.COMPILER_OPTIONS, which the forward and
    gradient rows are timed with) leave every metric bit for bit as the same chunked program
    computes it without them, float32 and float64: W1 (its 6 V limit clipping) and a
    diverging loop (kp < 0, no limit). (Against a program of another shape, such as a plain
    vmap of the 16 runs, loops compiled whole round differently: jaxcart.xlaflags.)"""
    import jaxcart.batch_metrics
    from jaxcart.batch_metrics import COMPILER_OPTIONS, step_metrics_batch

    assert jax.default_backend() != "cpu" or COMPILER_OPTIONS["cpu"]
    unlimited = jaxcart.PID(tau=bench.TAU, sample_time=bench.SAMPLE_TIME)
    for dtype in (jnp.float32, jnp.float64):
        with jax.enable_x64(dtype == jnp.float64):
            plant, w1, experiment = bench.w1_problem(HORIZON)
            for controller, gains in (
                (w1, bench.w1_gains(16)),
                (unlimited, np.array([[-4000.0, 0.0, 0.0], [40.0, 5.0, 0.0]])),
            ):
                tuned = step_metrics_batch(plant, controller, experiment, gains, dtype=dtype)
                with monkeypatch.context() as m:
                    m.setattr(jaxcart.batch_metrics, "COMPILER_OPTIONS", {})
                    plain = step_metrics_batch(plant, controller, experiment, gains, dtype=dtype)
                for name, a, b in zip(tuned._fields, tuned, plain, strict=True):
                    np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=name)
                if controller is w1:
                    assert (tuned.saturation_time > 0).any()  # the clip is exercised
                else:
                    assert tuned.diverged.tolist() == [True, False]


def test_command_line(result, monkeypatch, tmp_path, capsys):
    """`jaxcart bench --json OUT --quick` prints the table and writes (and rewrites) OUT."""
    calls = []

    def fake(**kwargs):
        calls.append(kwargs)
        return result

    monkeypatch.setattr(bench, "run_bench", fake)
    out = tmp_path / "bench.json"
    out.write_text("{}")  # an old result is kept unless --force
    assert main(["bench", "--quick", "--json", str(out), "--batch", "300"]) == 2
    assert "--force" in capsys.readouterr().err and out.read_text() == "{}"
    assert main(["bench", "--quick", "--json", str(out), "--batch", "300", "--force"]) == 0
    assert calls == [{"batch": 300, "quick": True}]
    table = capsys.readouterr().out
    for name in ("jaxcart", "python-control", "scipy", "numpy-vectorized", "grad", "grid"):
        assert name in table
    assert "jaxcart-float64" in table and "c-kernel" in table
    written = json.loads(out.read_text())
    assert [row["name"] for row in written["rows"]][0] == "jaxcart"
    assert written["grad_sims_per_s"] == result["grad_sims_per_s"]


def test_command_line_errors(monkeypatch, tmp_path, capsys):
    assert main(["bench", "--batch", "0"]) == 2
    assert "--batch 0" in capsys.readouterr().err
    assert main(["bench", "--json", str(tmp_path / "missing" / "b.json")]) == 2
    assert "does not exist" in capsys.readouterr().err

    def disagree(**kwargs):
        raise bench.PeerDisagreement("scipy disagrees")

    monkeypatch.setattr(bench, "run_bench", disagree)
    assert main(["bench"]) == 1
    assert "FAILED: scipy disagrees" in capsys.readouterr().err


def test_grid_ranges_are_those_of_jaxcart_grid():
    """The benchmark's 64^3 grid spans the default ranges of ``jaxcart grid``."""
    from tuning.commands.grid import DEFAULT_RANGES

    for name, text in DEFAULT_RANGES.items():
        lo, hi, _ = text.split(":")
        assert (float(lo), float(hi)) == bench.GRID_RANGES[name]


def test_peers_model_an_amplifier_saturation_as_the_simulators_do():
    """A plant with an amplifier limit below the software's: every peer clips at v_sat and agrees
    with the exact simulator; a plant with an effect the peers do not model is refused."""
    from jaxcart.exact import simulate_exact

    with jax.enable_x64(True):
        plant = jaxcart.handout_plant(v_sat=4.0)
        controller = jaxcart.PID(kp=80.0, kd=5.0, tau=0.01, v_limit=6.0)
        experiment = jaxcart.step(0.5, horizon=0.3)
        gains = np.array([80.0, 5.0, 0.0])
        exact = simulate_exact(plant, controller, experiment).position
        y_ivp, _ = peers.scipy_run(plant, controller, experiment, gains)
        assert np.max(np.abs(np.asarray(y_ivp)[: exact.size] - exact)) < 1e-6
        with pytest.raises(ValueError, match="coulomb"):
            peers.scipy_run(jaxcart.handout_plant(f_c=0.3), controller, experiment, gains)


# ---------------------------------------------------------------- the C kernel (ceiling row)

needs_cc = pytest.mark.skipif(ckernel.compiler() is None, reason="no C compiler on PATH")


@needs_cc
def test_c_kernel_computes_w1(result):
    """The kernel against float64 jaxcart.simulate (EXACT_FORMS) on the check runs: positions
    within TOLERANCE (measured ~4e-13 m), times to the sample, overshoot to 1e-8 %; in float32
    against jaxcart float32 on the whole batch: rounding only (a crossing may move 3 samples)."""
    check = result["checks"]["c-kernel"]
    assert check["max_position_diff_m"] <= bench.TOLERANCE
    diff = check["max_metric_diff"]
    for key in ("rise_time", "settling_time", "saturation_time", "diverged"):
        assert diff[key] == 0.0, key
    assert diff["overshoot"] < 1e-8 and diff["peak_voltage"] < 1e-9
    diff = result["checks"]["c-kernel-float32-vs-jaxcart-float32"]["max_metric_diff"]
    assert diff["overshoot"] < 1e-3  # %
    assert diff["steady_state_error"] < 1e-5  # m
    assert diff["peak_voltage"] < 1e-3  # V
    for key in ("rise_time", "settling_time", "saturation_time"):
        assert diff[key] <= 3.5e-3, key  # s
    assert diff["diverged"] == 0.0


@needs_cc
def test_c_kernel_scalar_loop_and_divergence():
    """The scalar loop and the vectorized blocks agree (1e-12 m: only FMA contraction differs),
    a batch that is not a multiple of the block is complete, and an unstable loop (no limit,
    kp < 0) is reported diverged with infinite times, as jaxcart reports it."""
    with jax.enable_x64(True):
        plant, controller, experiment = bench.w1_problem(HORIZON)
        unlimited = jaxcart.PID(tau=bench.TAU, sample_time=bench.SAMPLE_TIME)
        gains = np.concatenate([bench.w1_gains(19), [[-4000.0, 0.0, 0.0]]])
        info, trace = ckernel.run_w1(plant, unlimited, experiment, gains, record=20)
        scalar, trace1 = ckernel.run_w1(plant, unlimited, experiment, gains, record=20, lanes=False)
        ref = bench.jaxcart_metrics(plant, unlimited, experiment, gains, jnp.float64)
    np.testing.assert_allclose(trace[:19], trace1[:19], rtol=0, atol=1e-12)
    assert info["diverged"].tolist() == [False] * 19 + [True]
    assert ref["diverged"].tolist() == info["diverged"].tolist()
    assert np.isinf(info["rise_time"][-1]) and np.isinf(info["settling_time"][-1])
    assert max(bench._max_diff(info, scalar).values()) < 1e-9
    assert max(bench._max_diff({k: v[:19] for k, v in info.items()},
                               {k: v[:19] for k, v in ref.items()}).values()) < 1e-9  # fmt: skip
    with pytest.raises(ValueError, match="coulomb"):
        ckernel.run_w1(jaxcart.handout_plant(f_c=0.3), controller, experiment, gains)


def test_c_kernel_skipped_without_a_compiler(monkeypatch, tmp_path, result):
    """No compiler: the row says why (and the table prints it); a compiler that fails says so."""
    monkeypatch.setattr(ckernel, "_LOADED", {})
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    monkeypatch.delenv("CC", raising=False)
    assert ckernel.compiler() is None
    row = bench._c_kernel(None, None, None, None, None, {}, lambda m: None)
    assert row == {"name": "c-kernel", "skipped": "no C compiler on PATH (looked for $CC, cc, "
                   "gcc, clang)"}  # fmt: skip
    skipped = dict(result, rows=[*result["rows"][:2], row, *result["rows"][3:]])
    assert "c-kernel                  skipped: no C compiler" in bench.format_table(skipped)
    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\necho 'fake cc 1.0'\necho 'w1.c: error: no' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    with pytest.raises(ckernel.KernelUnavailable, match="did not build w1.c.*error: no"):
        ckernel.load()


@needs_cc
def test_c_kernel_is_built_once_into_the_cache(monkeypatch, tmp_path):
    """The library lands in the user's cache folder beside the JAX cache and is reused."""
    monkeypatch.setattr(ckernel, "_LOADED", {})
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    _, build = ckernel.load()
    path = tmp_path / "jaxcart" / "ckernel"
    assert build["path"].startswith(str(path)) and build["flags"][0] == "-O3"
    assert [p.suffix for p in path.iterdir()] == [".so"]  # no temporary file left behind
    stamp = (path / build["path"].rsplit("/", 1)[1]).stat().st_mtime_ns
    monkeypatch.setattr(ckernel, "_LOADED", {})
    assert ckernel.load()[1]["path"] == build["path"]
    assert (path / build["path"].rsplit("/", 1)[1]).stat().st_mtime_ns == stamp
