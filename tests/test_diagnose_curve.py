"""Friction read as a curve of the speed, the diagnosis's last candidate
(tuning/estimation/diagnose/friction_curve.py): named where it predicts held-out recordings
better, on data of the independent generator whose friction has a shape no named effect has;
and the rule that keeps it from being named otherwise."""

from __future__ import annotations

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
    assert fc["held_out"]["curve_sse"] < 0.5 * fc["held_out"]["named_sse"]
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


def _held(named, curve):
    return {"recordings": ["a", "b"], "named": [], "curve": [], "samples": [1, 1],
            "named_sse": named, "curve_sse": curve}  # fmt: skip


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
