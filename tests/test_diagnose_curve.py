"""Friction read as a curve of the speed, the diagnosis's last candidate
(tuning/estimation/diagnose/friction_curve.py): named where it predicts held-out recordings
better, on data of the independent generator whose friction has a shape no named effect has;
and the rule that keeps it from being named otherwise."""

from __future__ import annotations

import numpy as np
import pytest

from jaxcart.files import read_experiment
from tuning.estimation.diagnose import diagnose, friction_curve, render_markdown
from tuning.verification import REALISTIC, TrueCart, make_recording
from tuning.verification import experiments as ex

#: Sliding friction that rises with the speed to a plateau, 0.3 N more moving right and 0.15 N
#: more moving left (TrueCart's rise: 1 - exp(-|y'| / 3 cm/s) of it), over Coulomb's 0.3 N.
RISE = {"B_eq": 4.6, "f_c": 0.3, "rise_pos": 0.3, "rise_neg": 0.15, "v_rise": 0.03}


@pytest.fixture(scope="module")
def rise_taps(tmp_path_factory):
    """Two taps each way (0.6 and 0.4 m/s) on the independent generator, what real recordings
    carry included: each direction determined by two recordings, so each can be held out."""
    folder = tmp_path_factory.mktemp("rise")
    truth = TrueCart.from_values(RISE, motor_connected=False)
    art = REALISTIC.replace(gain_spread=0.0, limit_spread=0.0)
    paths = [
        make_recording(truth, ex.tap(speed=v), folder / f"tap{i}.toml", art, seed=i + 1).path
        for i, v in enumerate((0.6, -0.6, 0.4, -0.4))
    ]
    return truth, [read_experiment(p) for p in paths]


def test_rising_friction_is_read_as_a_curve_and_named(rise_taps, tmp_path):
    """No named structure explains the taps (Coulomb friction by direction is the best,
    0.03-0.08 mm held out); the curve predicts each tap held out to 0.007-0.014 mm, 0.04 of the
    named structure's sum of squares (named under 0.5), and its friction at 80 and 320 mm/s
    lies within 0.03 N of the truth's each way (measured 0.02 N at most)."""
    truth, recordings = rise_taps
    d = diagnose(recordings, progress=False, curve=True)
    assert not d.explained
    fc = d.friction_curve
    assert fc["named"], fc["why"]
    assert fc["held_out"]["curve_sse"] < 0.5 * fc["held_out"]["curve_named_sse"]
    c = fc["curve"]
    for side, direction in (("right", 1), ("left", -1)):
        for q, level, band in zip(c["speeds"], c["levels"][side], c["bands"][side], strict=True):
            if q >= 0.08:
                assert band is not None and band < 0.03, (side, q, band)
                want = truth.kinetic(direction) + truth.rise(direction, q)
                assert level == pytest.approx(want, abs=0.03), (side, q)
    assert "rises" in fc["words"] and "higher moving right" in fc["words"]
    assert d.curve_plant is not None and "friction_curve" in d.curve_plant.structure
    text = render_markdown(d, curve_files={"figure": "friction_curve.png"})
    assert "## Friction as a curve of the speed" in text and "**Named**" in text


def _held(named, curve, label="curve"):
    return {"recordings": ["a", "b"], "named": [], label: [], "samples": [1, 1],
            "named_sse": named, f"{label}_sse": curve, f"{label}_named_sse": named,
            f"{label}_count": 2}  # fmt: skip


def test_the_curve_is_named_only_where_it_predicts_better_and_departs():
    """The rule: held-out sum of squares at most half the named structure's, and an entry
    that departs from the slow level; one recording (nothing held out): shown, never named."""
    departs = [("f_curve_right[1]", 0.2, 12.0)]
    assert friction_curve.decide(_held(1.0, 0.4), departs)[0]
    assert not friction_curve.decide(_held(1.0, 0.6), departs)[0]
    assert not friction_curve.decide(_held(1.0, 0.1), [])[0]
    named, why = friction_curve.decide(None, departs)
    assert not named and "held out" in why
    # Friction that pushes the cart along (below 0) is never named, however well it predicts.
    c = friction_curve.Curve(
        (0.0, 0.005, 0.02, 0.08, 0.32),
        {"left": [0.59, 0.59, -0.27, 0.3, 0.3]},
        {"left": [0.08, 0.08, 0.1, 0.1, None]},
        0.86,
    )
    pushes = friction_curve.below_zero(c)
    assert pushes == [("left", 0.02, -0.27)]
    named, why = friction_curve.decide(_held(1.0, 0.1), departs, pushes)
    assert not named and "below 0" in why


def test_sides_slid_reads_the_directions_faster_than_the_first_entry(rise_taps):
    _, recordings = rise_taps
    assert friction_curve.sides_slid(recordings[:1]) == ("right",)
    assert friction_curve.sides_slid(recordings[1:2]) == ("left",)
    assert friction_curve.sides_slid(recordings) == ("right", "left")


def test_a_curve_is_described_in_words():
    c = friction_curve.Curve(
        (0.0, 0.005, 0.02, 0.08, 0.32),
        {"right": [0.6, 0.6, 0.5, 0.42, 0.4], "left": [0.6, 0.6, 0.55, 0.46, 0.45]},
        {"right": [0.01] * 5, "left": [0.01] * 4 + [None]},
        1.5,
    )
    words = friction_curve.describe(c)
    assert "moving right, friction falls from 0.60 N at 5 mm/s to 0.40 N at 32 cm/s" in words
    # The left side's last entry was held: its words stop at the last determined one.
    assert "to 0.46 N at 8 cm/s" in words


def test_the_curve_replaces_the_mechanics_forces_and_keeps_the_drive():
    """The curve's structure: the named drive (a saturation and a current limit per run, a
    delay, an offset) and dry friction stay; a spring, a tilt and viscous friction by direction
    (what a search reaches for where friction's shape is missing) give way to the tables."""
    from types import SimpleNamespace

    names = ("B_eq", "f_c", "delay", "v_offset", "k_s", "y_rest", "f_tilt", "B_asym")
    d = SimpleNamespace(
        parameters={n: {"value": 1.0} for n in names},
        per_recording={"p50": {"parameters": {"v_sat": {}, "i_max": {}}}, "tap": {}},
    )
    named, curve, per_run = friction_curve.structures(d, ("right",))
    assert set(named) == {*names, "v_sat", "i_max"}
    assert curve == ("B_eq", "f_c", "delay", "v_offset", "v_sat", "i_max", "f_curve_right")
    assert per_run == ("v_sat", "i_max")
    # Nor does a replaced force stay in the curve's cart at its named value (held, as a value
    # given and not fitted would be).
    start = friction_curve._without_replaced({n: 1.0 for n in names})
    assert set(start) == {"B_eq", "f_c", "delay", "v_offset"}


def _track(levels, se, span=(-0.3, 0.3)):
    """A read curve along the track at -0.3, -0.2, 0, 0.2, 0.3 m, independent errors ``se``."""
    n = len(levels)
    cov = (se**2 * np.eye(n)).tolist()
    return {"positions": [-0.3, -0.2, 0.0, 0.2, 0.3][:n], "levels": levels, "bands": [se] * n,
            "covariance": cov, "span": list(span), "b_eq": 4.6}  # fmt: skip


def test_friction_along_the_track_varies_where_two_positions_differ_by_3_se():
    """track_curve's rule beside the speed curve's: friction at two positions apart by 0.02 N
    and 3 standard errors of the difference shows friction that varies along the track; the
    words name the least and the most."""
    from tuning.estimation.diagnose import track_curve

    assert track_curve.varies(_track([0.3, 0.3, 0.31, 0.3, 0.3], 0.01)) == []
    assert "does not vary along the track" in friction_curve.decide(None, [], label="track")[1]
    rising = _track([0.2, 0.2, 0.25, 0.6, 0.6], 0.02)
    pairs = track_curve.varies(rising)
    assert (-0.2, 0.2, pytest.approx(0.4), pytest.approx(0.4 / (0.02 * 2**0.5))) in pairs
    # Correlated errors: two positions that move together differ with a smaller error.
    tied = {**rising, "covariance": (0.02**2 * (0.5 * np.eye(5) + 0.5)).tolist()}
    assert dict(((a, b), z) for a, b, _, z in track_curve.varies(tied))[(-0.2, 0.2)] == (
        pytest.approx(0.4 / 0.02)
    )
    words = track_curve.describe(rising)
    assert "least 0.20 N at -0.30 m, most 0.60 N at +0.20 m" in words
    assert friction_curve.decide(_held(1.0, 0.3, "track"), pairs, label="track")[0]
    assert not friction_curve.decide(_held(1.0, 0.6, "track"), pairs, label="track")[0]


def test_the_track_curve_is_tried_where_the_recordings_cover_the_track():
    """0.4 m covered together (two knot spacings), each run from where it started; the curve
    gives Coulomb's level over to the knots, each starting at the named f_c."""
    from types import SimpleNamespace

    from tuning.estimation.diagnose import track_curve

    runs = [SimpleNamespace(position=[0.0, 0.25]), SimpleNamespace(position=[0.0, -0.1])]
    assert track_curve.covered(runs[:1]) is None
    assert track_curve.covered(runs) is None  # 0.35 m
    runs.append(SimpleNamespace(position=[0.0, -0.2]))
    assert track_curve.covered(runs) == (-0.2, 0.25)
    kept = ("B_eq", "f_c", "delay", "deadzone")
    params, held = track_curve.structure(kept, kept, (1, 2), {"f_c": 0.35})
    assert params == ("B_eq", "delay", "deadzone", "f_track[1]", "f_track[2]")
    assert held == {"f_c": 0.0, "f_track": (0.35,) * 5}
    # A named f_c of 0 N starts the levels at the declared start, not at 0.
    assert track_curve.structure(kept, kept, (1, 2), {"f_c": 0.0})[1]["f_track"] == (0.3,) * 5
    # Without Coulomb friction named, the dead band stood in for its level: the curve takes it.
    params, held = track_curve.structure(kept[2:], kept, (1, 2), {"deadzone": 0.2})
    assert params == ("B_eq", "delay", "f_track[1]", "f_track[2]")
    assert held == {"f_c": 0.0, "deadzone": 0.0, "f_track": (0.3,) * 5}


def test_the_track_curve_fits_the_knots_every_fold_reaches():
    """The levels fitted: at the knots within 3/8 of a spacing (0.075 m) of the stretch that
    every recording but one covers, so that each fold fits the same curve."""
    from types import SimpleNamespace

    from tuning.estimation.diagnose import track_curve

    def runs(*spans):
        return [SimpleNamespace(position=[lo, hi]) for lo, hi in spans]

    # Each fold covers at least -0.14..0.24 m: the knots at -0.2, 0, +0.2 m.
    assert track_curve.fitted_knots(runs((0, 0.24), (-0.25, 0), (-0.14, 0.28))) == (1, 2, 3)
    # Every fold covers +-0.3 m: the knots at +-0.4 m are beyond reach.
    both = runs((0, 0.3), (-0.3, 0), (-0.15, 0.3), (-0.3, 0.15))
    assert track_curve.fitted_knots(both) == (1, 2, 3)
    # Two runs, one each way: each fold is one run, and the two share only 0 m.
    assert track_curve.fitted_knots(runs((0, 0.3), (-0.3, 0))) == (2,)
    assert track_curve.fitted_knots(runs((-0.35, 0.35))) == (0, 1, 2, 3, 4)


#: Friction rising along the track, 0.4 N more from +0.2 m on than before -0.2 m (a table,
#: linear between its points: not the curve's smooth map, which holds it within 0.018 N over
#: +-0.3 m at best), over Coulomb's 0.2 N.
ALONG = {"B_eq": 4.6, "f_c": 0.2, "track_y": (-0.4, -0.2, 0.2, 0.4), "track_f": (0, 0, 0.4, 0.4)}


@pytest.fixture(scope="module")
def along_runs(tmp_path_factory):
    """PD steps to +-0.25 m and out to 0.3 m and back to -0.15 m (1 s each) on the
    independent generator, what real recordings carry included: together they cover 0.55 m
    of the track, and any two of them 0.45 m or more."""
    from jaxcart import PID

    folder = tmp_path_factory.mktemp("along")
    truth = TrueCart.from_values(ALONG)
    art = REALISTIC.replace(gain_spread=0.0, limit_spread=0.0)
    pid = PID(kp=40.0, kd=2.0)
    runs = (ex.step(pid, 0.25, horizon=1.0), ex.step(pid, -0.25, horizon=1.0),
            ex.square(pid, 0.3, period=1.0, horizon=1.0, low=-0.15))  # fmt: skip
    paths = [
        make_recording(truth, e, folder / f"run{i}.toml", art, seed=i + 1).path
        for i, e in enumerate(runs)
    ]
    return truth, [read_experiment(p) for p in paths]


def test_friction_along_the_track_is_read_as_a_curve_and_named(along_runs):
    """After Coulomb friction alone (the handout's model, as a named structure), the curve of
    the position predicts each run held out better (0.07 of the named structure's sum of
    squares), is named, and its levels at the knots it fitted (-0.2, 0, 0.2 m: within reach of
    every two runs) lie within 0.05 N of the truth's friction there (measured 0.019 N)."""
    from types import SimpleNamespace

    from tuning.estimation.diagnose.suite import _track_right

    truth, recordings = along_runs
    d = SimpleNamespace(parameters={"B_eq": {"value": 4.6}, "f_c": {"value": 0.4}},
                        per_recording={})  # fmt: skip
    found = friction_curve.discover(recordings, d)
    track, held = found["track"], found["held_out"]
    assert track["named"], track["why"]
    assert held["track_count"] == 3 and held["track_sse"] < 0.5 * held["track_named_sse"]
    assert track["curve"]["positions"] == pytest.approx([-0.2, 0.0, 0.2])
    assert _track_right(track, truth)
    assert "track_friction" in found["plant"].structure
