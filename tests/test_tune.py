"""Gradient PID tuning (tuning/design/: tune.py, its modules, losses.py; tuning/commands/tune.py).

Every claim about a tuned controller is re-checked here on the exact simulator
(jaxcart.exact.simulate_exact + jaxcart.metrics.step_info), independently of the tuner's own
report. Iteration budgets are cut to keep the file fast; the tuner stops early anyway.
"""

import importlib
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from hw.gains import read_gains
from jaxcart.errors import UserError
from jaxcart.exact import simulate_exact
from jaxcart.metrics import step_info
from tuning.benchmark.tuners import compare_tuners
from tuning.design.losses import LossSettings, Spec, make_loss
from tuning.design.problem import DEFAULT_BOUNDS
from tuning.design.tune import tune

STEP = jc.step(0.5, horizon=3.0)
iteration_module = importlib.import_module("tuning.design.iteration")


def exact_metrics(plant, pid, experiment=STEP):
    return step_info(simulate_exact(plant, pid, experiment), v_limit=6.0)


@pytest.fixture(scope="module")
def lab():
    """The lab's design problem with the default settings (fewer iterations)."""
    return tune(max_iterations=160)


def test_default_problem_meets_the_lab_spec_on_the_exact_simulator(lab):
    info = exact_metrics(jc.handout_plant(), lab.gains)
    assert lab.meets and lab.failing == ()
    assert info.settling_time < 1.0 and info.overshoot < 5.0
    # The tuner's report is the exact simulator's.
    assert lab.exact.settling_time == pytest.approx(info.settling_time, abs=1e-12)
    assert lab.exact.overshoot == pytest.approx(info.overshoot, abs=1e-9)
    # The target: 0.85 s or less (the bang-bang bound is about 0.75 s for stopping at
    # 0.5 m; entering the 1 cm band is a little faster).
    print(
        f"\nlab problem: exact settling {info.settling_time:.3f} s, overshoot "
        f"{info.overshoot:.2f} %, <= 0.85 s: {info.settling_time <= 0.85}"
    )
    assert info.settling_time <= 0.85
    assert info.settling_time > 0.6  # sanity: physically impossible below ~0.7 s


def test_default_problem_keeps_every_controller_setting(lab):
    g = lab.gains
    assert (g.tau, g.v_limit, g.sample_time, g.derivative_on, g.anti_windup) == (
        0.01,
        6.0,
        0.001,
        "error",
        "none",
    )
    for name in ("kp", "kd", "ki"):
        lo, hi = lab.bounds[name]  # the box: kp and kd's upper ends derived from the cart
        assert lo <= getattr(g, name) <= hi
    assert lab.bounds["kp"] == (DEFAULT_BOUNDS["kp"][0], pytest.approx(600.0))
    assert lab.seconds_to_spec is not None and lab.seconds_to_spec <= lab.seconds
    h = lab.history
    assert len(h) == lab.iterations and h[0]["scale"] == 1.0 and h[-1]["scale"] < 1.0
    # The smooth simulator at the final widths agrees with the exact one to a few samples.
    assert lab.smooth.settling_time == pytest.approx(lab.exact.settling_time, abs=0.01)
    assert lab.smooth.overshoot == pytest.approx(lab.exact.overshoot, abs=0.2)
    doc = lab.to_json()
    assert set(doc["exact"]) == {"settling_time", "overshoot", "rise_time", "steady_state_error"}
    json.dumps(doc, allow_nan=False)


def test_pd_keeps_ki_zero():
    res = tune(free=("kp", "kd"), max_iterations=80, n_starts=4)
    assert res.gains.ki == 0.0
    info = exact_metrics(jc.handout_plant(), res.gains)
    assert res.meets and info.settling_time < 1.0 and info.overshoot < 5.0
    # Other starts, free gains (as many) and bounds reuse the one compiled iteration.
    update = iteration_module._CACHE[next(reversed(iteration_module._CACHE))]
    traced = update.cache_size()
    tune(
        start=(60.0, 4.0, 1.0),
        free=("kp", "ki"),
        bounds={"kp": (1.0, 500.0)},
        max_iterations=6,
        n_starts=4,
    )
    assert update.cache_size() == traced


def test_impossible_spec_reports_the_failing_constraint():
    # 0.5 s is below the physical limit (~0.7 s to enter the band with 6 V).
    res = tune(spec=Spec(settling_time=0.5), max_iterations=40, n_starts=2, patience=5)
    assert not res.meets
    assert "settling_time" in res.failing and "overshoot" not in res.failing
    assert "cannot meet" in res.message and "settling time" in res.message
    assert res.seconds_to_spec is None
    info = exact_metrics(jc.handout_plant(), res.gains)
    assert info.settling_time >= 0.5  # the best effort, honestly reported
    assert res.exact.settling_time == pytest.approx(info.settling_time)


def test_robust_tuning_reports_the_true_worst_case():
    ranges = {"B_eq": (4.0, 7.0), "M": (0.9, 1.1)}
    res = tune(robust=ranges, max_iterations=60, n_starts=2, n_check=2, patience=10)
    assert len(res.plant_set) == 5 + 2  # centre + 4 corners, + 2 random
    worst_s, worst_o = 0.0, 0.0
    for entry in res.plant_set:
        plant = jc.handout_plant().replace(**entry["params"])
        info = exact_metrics(plant, res.gains)
        assert entry["exact"]["settling_time"] == pytest.approx(info.settling_time)
        worst_s, worst_o = max(worst_s, info.settling_time), max(worst_o, info.overshoot)
    assert res.worst.settling_time == pytest.approx(worst_s)
    assert res.worst.overshoot == pytest.approx(worst_o)
    # Meets on every plant of the set, or says which constraint fails.
    assert res.meets == (worst_s < 1.0 and worst_o < 5.0)
    assert res.meets or res.failing
    print(
        f"\nrobust (B_eq 4..7, M +/-10 %): worst settling {worst_s:.3f} s, overshoot "
        f"{worst_o:.2f} %"
    )


def test_loss_gradient_matches_central_differences():
    spec, settings = Spec(), LossSettings()
    pid = jc.PID(v_limit=6.0)
    loss = make_loss(pid, jc.step(0.5, horizon=spec.horizon), spec, settings, robust=False)
    fixed = jnp.asarray([40.0, 5.0, 5.0])
    mask = jnp.asarray([True, True, True])
    plant = jc.handout_plant()

    def f(theta, scale):
        return loss(theta, fixed, mask, plant, scale)[0]

    value = jax.jit(f)
    grad = jax.jit(jax.grad(f))
    # A feasible point (hinges off) and an infeasible one (hinges on), two widths.
    for gains, scale in (((100.0, 6.0, 2.0), 1.0), ((40.0, 5.0, 5.0), 0.5)):
        theta = jnp.log(jnp.asarray(gains))
        g = np.asarray(grad(theta, scale))
        assert np.all(np.isfinite(g)) and np.any(g != 0)
        h = 1e-5
        for j in range(3):
            e = jnp.zeros(3).at[j].set(h)
            fd = (float(value(theta + e, scale)) - float(value(theta - e, scale))) / (2 * h)
            assert g[j] == pytest.approx(fd, rel=1e-3, abs=1e-6 * np.abs(g).max()), (gains, j)


def test_bad_input_is_a_user_error():
    with pytest.raises(UserError, match="free gains"):
        tune(free=("kx",))
    with pytest.raises(UserError, match="start gain kd"):
        tune(start=(40.0, -1.0, 0.0))
    with pytest.raises(UserError, match="bounds kp"):
        tune(bounds={"kp": (10.0, 1.0)})
    with pytest.raises(ValueError, match="settling_time"):
        Spec(settling_time=-1.0)


def test_command_line_writes_gains_and_refuses_to_overwrite(tmp_path, capsys):
    from tuning.commands.main import main

    out = tmp_path / "g.json"
    summary = tmp_path / "summary.json"
    args = [
        "tune",
        "--out",
        str(out),
        "--json",
        str(summary),
        "--iterations",
        "40",
        "--starts",
        "2",
        "--quiet",
        "--free",
        "kp,kd",
        "--settling",
        "1.2",
    ]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "exact simulator" in text and "smooth simulator" in text
    pid = read_gains(out)
    assert pid.ki == 0.0 and pid.v_limit == 6.0 and pid.tau == 0.01
    doc = json.loads(summary.read_text())
    assert set(doc) >= {"gains", "exact", "smooth", "seconds"}
    assert doc["gains"]["kp"] == pid.kp
    assert doc["exact"]["settling_time"] < 1.2
    info = exact_metrics(jc.handout_plant(), pid)
    assert doc["exact"]["settling_time"] == pytest.approx(info.settling_time)
    assert out.with_suffix(".png").stat().st_size > 10_000
    # A second run refuses before tuning: exit 2, one line naming the file and --force.
    before = out.read_text()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--force" in err and err.count("\n") == 1
    assert out.read_text() == before


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--free", "kp,kx"], "--free"),
        (["--start", "40,5"], "--start"),
        (["--settling", "nan"], "--settling"),
        (["--range", "B_eq=3,7"], "--range needs --robust"),
        (["--robust", "--range", "B_eq=7,3"], "LO <= HI"),
        (["--plant", "missing.toml"], "no such file"),
    ],
)
def test_command_line_bad_input(tmp_path, capsys, argv, words):
    from tuning.commands.main import main

    assert main(["tune", "--out", str(tmp_path / "g.json"), *argv]) == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1


def test_plant_option_reads_a_plant_file_and_its_effects(tmp_path):
    import argparse

    from tuning.commands.tune import _plant

    path = jc.write_plant_file(tmp_path / "p.toml", jc.build_plant({"B_eq": 4.8, "delay": 0.002}))
    args = argparse.Namespace(plant_file=str(path), B_eq=None, f_c=0.4, M=None)
    plant = _plant(args)
    assert plant.B_eq == 4.8 and plant.get("f_c") == 0.4 and plant.get("delay") == 0.002
    assert plant.structure == ("delay", "coulomb")
    (tmp_path / "bad.toml").write_text('format = "jaxcart-plant"\n[plant]\nB_eqq = 4.8\n')
    with pytest.raises(UserError, match="B_eqq"):
        _plant(
            argparse.Namespace(plant_file=str(tmp_path / "bad.toml"), B_eq=None, f_c=None, M=None)
        )


@pytest.mark.slow
def test_compare_tuners_runs_all_three_and_rechecks_on_the_exact_simulator():
    report = compare_tuners(seed=1)
    for key in ("gradient", "nelder_mead", "grid"):
        entry = report[key]
        g = entry["gains"]
        pid = jc.PID(kp=g["kp"], kd=g["kd"], ki=g["ki"], v_limit=6.0)
        info = exact_metrics(jc.handout_plant(), pid)
        assert entry["settling_time"] == pytest.approx(info.settling_time), key
        assert entry["meets"] == (info.settling_time < 1.0 and info.overshoot < 5.0)
    assert report["grid"]["seconds"] >= report["gradient"]["seconds"]  # equal wall time
    print("\n" + report["table"])


def test_the_optimizer_is_optax_adam_on_optax_cosine_decay_placed_like_the_update_output():
    """The tuner's optimizer, whose learning rate and iteration count are arguments of the
    compiled update, steps as optax.adam on optax.cosine_decay_schedule (to rounding), past the
    end of the decay too; its initial state is optax's, the moments placed by start (where
    the update puts them, so the second step compiles nothing)."""
    import optax

    from jaxcart.parallel import batch_sharding
    from tuning.design.iteration import ALPHA, initial_state, optimizer

    rng = np.random.default_rng(1)
    lr, n = 0.25, 7
    ours = optimizer(lr, float(n))
    theirs = optax.adam(optax.cosine_decay_schedule(lr, n, alpha=ALPHA))
    theta = jnp.asarray(rng.normal(size=(8, 6)))
    rows = batch_sharding()
    state, expected = initial_state(theta, rows), theirs.init(theta)
    assert jax.tree.structure(state) == jax.tree.structure(expected)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(expected), strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        if a.ndim == 2:
            assert a.sharding == rows
    for _ in range(n + 2):
        grad = jnp.asarray(rng.normal(size=(8, 6)))
        step, state = ours.update(grad, state)
        want, expected = theirs.update(grad, expected)
        np.testing.assert_allclose(np.asarray(step), np.asarray(want), rtol=1e-13, atol=0)
