"""Gain grids (tuning.design.grid, ``jaxcart grid``) against the stored-response reference:
jaxcart.step_info on jaxcart.simulate in float64 with the exact (hard clip) forms."""

import argparse
import dataclasses
import hashlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from hw.atomicio import OutputError
from jaxcart.errors import UserError
from tuning.commands import grid as grid_cmd
from tuning.design import grid, grid_blocks

TS = 1e-3  # sample time [s]: the tolerance of every time metric is one sample
OVERSHOOT_TOL = 0.05  # [percentage points], float32 against float64
SPEC = dict(settling_time=1.0, overshoot=5.0)
# A small grid across the feasible boundary: slow, fast, oscillating and windup points.
KP, KD, KI = np.array([30.0, 80.0, 130.0]), np.array([1.0, 4.0, 9.0]), np.array([0.0, 6.0])
TIMES = ("rise_time", "settling_time", "saturation_time")


@pytest.fixture(scope="module")
def setup():
    plant, controller = jc.handout_plant(), jc.PID(v_limit=6.0)
    experiment = jc.step(0.5, horizon=1.5)
    return plant, controller, experiment


@pytest.fixture(scope="module")
def reference(setup):
    """step_info of the stored float64 hard-clip run for one gain triple (jitted once)."""
    plant, controller, experiment = setup
    sim = jax.jit(lambda pid: jc.simulate(plant, pid, experiment, smoothing=jc.EXACT_FORMS))

    def info(gains):
        pid = dataclasses.replace(controller, kp=gains[0], kd=gains[1], ki=gains[2])
        return jc.step_info(sim(pid), v_limit=6.0)

    return info


@pytest.fixture(scope="module")
def grids(setup):
    """The small grid in float32 and float64 (in blocks of 8 points: 3 blocks, the last
    one short, reduced as they stream in)."""
    return {
        name: grid.grid_search(*setup, KP, KD, KI, dtype=dtype, block=block, **SPEC)
        for name, dtype, block in (("float32", jnp.float32, 64), ("float64", jnp.float64, 8))
    }


def _rows(result):
    return [(idx, StepRow(result, idx)) for idx in np.ndindex(result.shape)]


def StepRow(result, idx):  # noqa: N802 (reads as a constructor)
    return jc.StepInfo(*(v[idx].item() for v in result.info))


def test_random_points_match_step_info_float32(setup, reference):
    rng = np.random.default_rng(3)
    gains = rng.uniform([10.0, 0.0, 0.0], [150.0, 15.0, 10.0], size=(6, 3))
    result = grid.evaluate_list(*setup, gains, **SPEC)
    assert result.info.settling_time.dtype == np.float32
    for i, g in enumerate(gains):
        ref, got = reference(g), StepRow(result, (i,))
        for name in TIMES:
            assert getattr(got, name) == pytest.approx(getattr(ref, name), abs=TS * 1.001), name
        assert got.overshoot == pytest.approx(ref.overshoot, abs=OVERSHOOT_TOL)
        assert got.steady_state_error == pytest.approx(ref.steady_state_error, abs=1e-5)
        assert got.peak_voltage == pytest.approx(ref.peak_voltage, abs=1e-4)
        assert got.diverged == ref.diverged


def test_float64_grid_equals_reference_and_mask_is_meets(grids, reference):
    result = grids["float64"]
    assert result.shape == (KP.size, KD.size, KI.size)
    for idx, got in _rows(result):
        ref = reference(result.gains_at(idx))
        for name in (*TIMES, "overshoot", "steady_state_error", "peak_voltage"):
            assert getattr(got, name) == pytest.approx(getattr(ref, name), rel=1e-9, abs=1e-12)
        assert result.feasible[idx] == ref.meets(**SPEC)
    assert 0 < result.n_feasible < result.n_points  # the grid straddles the boundary


def test_best_point_is_brute_force_best(grids, reference):
    result = grids["float64"]
    points = [(reference(result.gains_at(i)), i) for i in np.ndindex(result.shape)]
    best = min((info.settling_time, info.overshoot, i) for info, i in points if info.meets(**SPEC))
    assert result.best_feasible
    assert result.best_index == best[2]
    assert result.best_gains == tuple(a[j] for a, j in zip((KP, KD, KI), best[2], strict=True))


def test_no_feasible_point_gives_closest(setup, reference):
    tight = dict(settling_time=0.3, overshoot=5.0)  # below the bang-bang bound (~0.75 s)
    result = grid.grid_search(*setup, KP, KD, KI, dtype=jnp.float64, **tight)
    assert result.n_feasible == 0 and not result.best_feasible
    violation = {}
    for i in np.ndindex(result.shape):
        ref = reference(result.gains_at(i))
        violation[i] = max(0, ref.settling_time / 0.3 - 1) + max(0, ref.overshoot / 5.0 - 1)
    assert violation[result.best_index] == min(violation.values())


def test_ties_in_settling_time_go_to_the_smaller_overshoot():
    flat = {
        "settling_time": np.array([0.8, 0.7, 0.7, 0.7, 0.6]),
        "overshoot": np.array([1.0, 3.0, 2.0, 4.0, 9.0]),
        "steady_state_error": np.zeros(5),
        "diverged": np.zeros(5, bool),
    }
    feasible = flat["overshoot"] < 5.0
    assert grid_blocks.best_of(flat, feasible, 1.0, 5.0) == (2, True)
    # None feasible (spec 0.5 s): least violation, ties broken by steady-state error.
    flat["settling_time"][:] = np.inf
    flat["steady_state_error"][:] = [3e-3, 2e-3, 1e-3, 1e-3, 4e-3]
    flat["diverged"][2] = True
    assert grid_blocks.best_of(flat, np.zeros(5, bool), 0.5, 5.0) == (3, False)


def test_float32_agrees_with_float64(grids):
    r32, r64 = grids["float32"], grids["float64"]
    for name in TIMES:
        a, b = getattr(r32.info, name), getattr(r64.info, name)
        np.testing.assert_array_equal(np.isinf(a), np.isinf(b))
        fin = np.isfinite(b)
        np.testing.assert_allclose(a[fin], b[fin], atol=TS * 1.001, rtol=0)
    diff = np.abs(r32.info.overshoot - r64.info.overshoot)
    assert diff.max() < OVERSHOOT_TOL
    # Really computed in float32, not silently in float64: with r = 0.5 m and y in [0.25, 1) m,
    # r - y of float32 numbers is a whole multiple of 2^-25 m.
    sse = r32.info.steady_state_error.astype(np.float64) * 2.0**25
    assert np.all(sse == np.round(sse)) and np.any(sse > 0)
    assert not np.all(
        r64.info.steady_state_error * 2.0**25 == np.round(r64.info.steady_state_error * 2.0**25)
    )
    np.testing.assert_array_equal(r32.feasible, r64.feasible)
    assert r32.best_index == r64.best_index


def test_sharded_chunks_equal_one_unsharded_batch(setup):
    assert len(jax.devices()) == 2
    plant, controller, experiment = setup
    kp, kd, ki = np.linspace(20, 140, 5), np.linspace(0.5, 12, 4), np.array([0.0, 1.0])
    # 40 points in chunks of 8 over 2 devices: several chunks per device and a padded block.
    sharded = grid.grid_search(*setup, kp, kd, ki, dtype=jnp.float64, chunk=8, **SPEC)
    gains = np.stack(np.meshgrid(kp, kd, ki, indexing="ij"), -1).reshape(-1, 3)

    def one(g):
        pid = dataclasses.replace(controller, kp=g[0], kd=g[1], ki=g[2])
        return jc.step_metrics(plant, pid, experiment, smoothing=jc.EXACT_FORMS)

    single = jax.jit(jax.vmap(one))(jnp.asarray(gains))
    for name in jc.StepInfo._fields:
        a, b = getattr(sharded.info, name).reshape(-1), np.asarray(getattr(single, name))
        if name in (*TIMES, "diverged"):  # whole samples: identical
            np.testing.assert_array_equal(a, b)
        else:  # XLA may fuse the two programs differently: rounding only
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


def test_exact_recheck_agrees_with_grid(setup, grids):
    result = grids["float32"]
    exact, label = grid.recheck(*setup, result.best_gains)
    got = result.best_info
    assert exact.settling_time == pytest.approx(got.settling_time, abs=TS * 1.001)
    assert exact.overshoot == pytest.approx(got.overshoot, abs=OVERSHOOT_TOL)
    assert "exact" in label
    table = grid.comparison(result, exact, label)
    assert "settling time [s]" in table and "meets specification" in table


def test_plot_marks_best_and_labels_units(grids, tmp_path):
    result = grids["float64"]
    path = tmp_path / "g.png"
    fig = grid.plot_slices(result, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    axes = [ax for ax in fig.axes if ax.get_visible() and ax.get_label() != "<colorbar>"]
    assert len(axes) == KI.size
    assert all(ax.get_ylabel() in ("$k_d$ [V s/m]", "") for ax in axes)
    assert any("[s]" in ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>")
    stars = [line for ax in axes for line in ax.get_lines() if line.get_marker() == "*"]
    assert len(stars) == 1
    assert tuple(stars[0].get_xydata()[0]) == result.best_gains[:2]
    with pytest.raises(OutputError, match="exists"):  # written atomically (hw.atomicio)
        grid.plot_slices(result, path)


# ---------------------------------------------------------------- the command


def _run(argv):
    parser = argparse.ArgumentParser(prog="jaxcart")
    grid_cmd.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["grid", *argv])
    return args.func(args)


SMALL = ["--kp", "40:120:3", "--kd", "3:9:3", "--ki", "0:2:2", "--horizon", "1.5"]


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_command_writes_npz_and_png_and_never_overwrites(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert _run(SMALL) == 0
    out = capsys.readouterr().out
    first, png = tmp_path / "jaxcart-out/grid.npz", tmp_path / "jaxcart-out/grid.png"
    assert first.is_file() and png.read_bytes()[:4] == b"\x89PNG"
    for text in ("feasible:", "best gains:", "points/s", "grid.npz", "grid.png"):
        assert text in out
    # The best kp is the grid's largest: said, with the advice; the blocks are cleaned up.
    assert "on a bound: kp is at the upper end of its range (120); widen it" in out
    assert not (tmp_path / "jaxcart-out/grid-blocks").exists()
    with np.load(first) as data:
        assert data["settling_time"].shape == (3, 3, 2) == data["feasible"].shape
        assert data["feasible"].sum() == int(out.split("feasible: ")[1].split()[0])
        best = tuple(data["best_index"])
        assert data["exact_settling_time"] == pytest.approx(data["settling_time"][best], abs=TS)
    digests = (_digest(first), _digest(png))

    assert _run(SMALL) == 0  # the second run gets new names
    assert (tmp_path / "jaxcart-out/grid-2.npz").is_file()
    assert (tmp_path / "jaxcart-out/grid-2.png").is_file()
    assert (_digest(first), _digest(png)) == digests

    with pytest.raises(UserError, match="--out .*grid.npz exists"):
        _run([*SMALL, "--out", str(first)])
    assert _digest(first) == digests[0]
    assert _run([*SMALL, "--out", str(first), "--force", "--float64"]) == 0
    with np.load(first) as data:
        assert data["dtype"] == "float64" and data["overshoot"].dtype == np.float64


def test_command_with_a_gains_file(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "list.csv").write_text("# candidates\nkd,kp,ki\n4,60,0\n5,90,0\n1,20,3\n")
    assert _run(["--gains-file", "list.csv", "--horizon", "1.5", "--out", "l.npz"]) == 0
    with np.load(tmp_path / "l.npz") as data:
        np.testing.assert_array_equal(data["gains"], [[60, 4, 0], [90, 5, 0], [20, 1, 3]])
        assert data["settling_time"].shape == (3,)
    assert (tmp_path / "l.png").is_file()
    assert "best gains: kp = " in capsys.readouterr().out


def test_a_step_beyond_the_track_is_refused_as_tune_refuses_it():
    from argparse import Namespace

    args = Namespace(step=5.0, horizon=3.0, settling=1.0, overshoot=5.0)
    with pytest.raises(UserError, match="--step 5: the cart travels at most 0.814 m"):
        grid_cmd._check_args(args)


@pytest.mark.parametrize(
    "option, text",
    [
        ("--kp", "10:5:4"),
        ("--kd", "0:2:0"),
        ("--ki", "-1:2:3"),
        ("--kp", "a:b:4"),
        ("--kd", "1:2"),
        ("--ki", "1:2:3.5"),
        ("--kp", "1:2:1"),
        ("--kd", "0:inf:3"),
    ],
)
def test_bad_ranges_name_the_option(option, text):
    with pytest.raises(UserError, match=f"^{option} "):
        grid_cmd.parse_range(option, text)


@pytest.mark.parametrize(
    "content, match",
    [
        ("kp,kd\n1,2\n", "column ki missing"),
        ("kp,kd,ki\n1,x,3\n", "line 2, column kd"),
        ("1,2,-3\n", "line 1, column kd"),  # no header: kp, ki, kd, the handout's order
        ("kp,kd,ki\n", "no rows"),
    ],
)
def test_bad_gains_files_say_where(tmp_path, content, match):
    path = tmp_path / "g.csv"
    path.write_text(content)
    with pytest.raises(UserError, match=match):
        grid_cmd.read_gains_file(path)


def test_cli_reports_bad_option_in_one_line(capsys):
    from tuning.commands.main import main

    assert main(["grid", "--kp", "150:10:64"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxcart grid: error: --kp '150:10:64'") and "\n" not in err


# ---------------------------------------------------------------- blocks, checkpoints, streaming


class _Stop(Exception):
    pass


@pytest.fixture(scope="module")
def blocked(grids):
    """The small grid (18 points) in float64 in blocks of 8."""
    return grids["float64"]


def _assert_same(a, b):
    for name in jc.StepInfo._fields:
        np.testing.assert_array_equal(getattr(a.info, name), getattr(b.info, name), name)
    np.testing.assert_array_equal(a.feasible, b.feasible)
    assert (a.best_index, a.best_feasible, a.best_info) == (
        b.best_index,
        b.best_feasible,
        b.best_info,
    )


def test_killed_run_resumes_from_its_blocks(setup, blocked, tmp_path, monkeypatch):
    calls = []
    real = grid.step_metrics_batch
    monkeypatch.setattr(
        grid, "step_metrics_batch", lambda *a, **k: calls.append(1) or real(*a, **k)
    )

    def killed_after_one_block(done, total):
        raise _Stop

    run = dict(dtype=jnp.float64, block=8, checkpoint=tmp_path, **SPEC)
    with pytest.raises(_Stop):
        grid.grid_search(*setup, KP, KD, KI, progress=killed_after_one_block, **run)
    (folder,) = tmp_path.iterdir()  # one folder, named by the problem's hash
    assert len(list(folder.glob("block-*.npz"))) == 1 and len(calls) == 1
    resumed = grid.grid_search(*setup, KP, KD, KI, **run)
    assert len(calls) == 3  # only the two missing blocks were computed
    _assert_same(resumed, blocked)
    # The same problem built again reuses every block; a changed one (another step) none.
    grid.grid_search(setup[0], setup[1], jc.step(0.5, horizon=1.5), KP, KD, KI, **run)
    assert len(calls) == 3
    grid.grid_search(setup[0], setup[1], jc.step(0.4, horizon=1.5), KP, KD, KI, **run)
    assert len(calls) == 6 and len(list(tmp_path.iterdir())) == 2
    resumed.store.remove()
    assert not folder.exists()


def test_streaming_reduction_equals_full_arrays(setup, blocked, tmp_path):
    streamed = grid.grid_search(
        *setup, KP, KD, KI, dtype=jnp.float64, block=8, keep_full=False, **SPEC
    )
    assert streamed.info is None and streamed.feasible is None
    assert (streamed.best_index, streamed.best_info) == (blocked.best_index, blocked.best_info)
    assert streamed.n_feasible == blocked.n_feasible
    np.testing.assert_array_equal(blocked.ki_feasible, blocked.feasible.sum(axis=(0, 1)))
    np.testing.assert_array_equal(streamed.ki_feasible, blocked.ki_feasible)
    ts, ok = streamed.slices([1])
    np.testing.assert_array_equal(ts, blocked.info.settling_time[:, :, [1]])
    np.testing.assert_array_equal(ok, blocked.feasible[:, :, [1]])
    # The .npz written block by block from the store holds the same arrays.
    grid.save_npz(streamed, tmp_path / "s.npz")
    grid.save_npz(blocked, tmp_path / "f.npz")
    with np.load(tmp_path / "s.npz") as s, np.load(tmp_path / "f.npz") as f:
        assert sorted(s.files) == sorted(f.files)
        for name in f.files:
            np.testing.assert_array_equal(s[name], f[name], name)
    assert grid.plot_slices(streamed) is not None


def test_best_on_a_bound_is_flagged_with_advice(blocked, tmp_path):
    inner = dataclasses.replace(blocked, best_index=(1, 1, 0))
    assert grid.edge_notes(inner) == []
    corner = dataclasses.replace(blocked, best_index=(2, 0, 0))
    notes = grid.edge_notes(corner)
    # kp at its top, kd at its bottom (1 > 0); ki at 0, a physical bound, is not flagged.
    assert len(notes) == 2 and all("widen it" in n for n in notes)
    assert notes[0].startswith("kp is at the upper end") and notes[1].startswith(
        "kd is at the lower"
    )
    import json

    grid.save_json(corner, tmp_path / "s.json")
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["on_edge"] == notes and doc["best_gains"] == {"kp": 130.0, "kd": 1.0, "ki": 0.0}
    assert "(on the range's bound: kp, kd)" in grid._title(corner)


def test_figure_says_which_ki_slices_it_shows(blocked):
    fig = grid.plot_slices(blocked)
    assert "all 2 $k_i$ slices shown" in fig._suptitle.get_text()
    many = dataclasses.replace(blocked, axes=(KP, KD, np.linspace(0.0, 30.0, 64)))
    note = grid.slice_note(many, [0, 21, 42, 63])
    assert note.startswith("$k_i$ slices shown: 4 of 64 (0, 10, 20, 30 V/(m s))")


@pytest.mark.parametrize(
    "argv, start",
    [
        (["--coordinator", "nohost", "--num-processes", "2", "--process-id", "0"], "--coordinator"),
        (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "5"], "--process-id"),
        (["--block", "0"], "--block 0"),
    ],
)
def test_cli_bad_distributed_options_in_one_line(capsys, argv, start):
    from tuning.commands.main import main

    assert main(["grid", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"jaxcart grid: error: {start}") and "\n" not in err
