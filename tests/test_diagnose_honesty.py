"""jaxcart diagnose says what it does not know: a recording no candidate explains, an effect
that is not significant, a parameter correction beside an effect, M and gamma_scale that one
closed loop cannot tell apart, and the forward selection past pairs (docs/diagnose.md).

The recordings are made as tuning/estimation/diagnose/suite.py makes its cases (the exact simulator
through the encoder, written as an experiment file and read back), 1 s long to keep each
diagnosis a few seconds. A truth with the ``quantization`` sensor effect has a controller that
reads whole encoder counts, as the hardware does; its recorded command shows it, and the
diagnosis's simulation then reads them too (docs/diagnose.md, "The encoder in the loop").
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import jaxcart as jc
from jaxcart.files import read_experiment
from jaxcart.plantspec import build_plant
from jaxcart.synthetic import make_recording, make_tap_recording, write_recording
from tuning.estimation.diagnose import diagnose, per_run, render_markdown
from tuning.estimation.diagnose.candidate_runs import fitter_scale
from tuning.estimation.diagnose.policy import (
    CORRECTION_MARGIN,
    K_MAX,
    MIN_COASTING,
    PLAUSIBLE,
    SIGNIFICANCE,
)
from tuning.estimation.diagnose.report import figure_title
from tuning.estimation.diagnose.result import Diagnosis
from tuning.estimation.diagnose.significance import implausible, significance
from tuning.estimation.diagnose.structures import (
    PER_RUN,
    Candidate,
    batchable,
    extend,
    structure,
    swapped_correction,
)
from tuning.estimation.diagnose.suite import TRACK_WAVE
from tuning.estimation.engine.covariance import covariance
from tuning.estimation.engine.noise import (
    MISFIT_RATIO,
    effective_samples,
    misfits,
    widened_for_model_error,
)
from tuning.estimation.engine.segments import prepare

Q = 2.275e-5
FLOOR = Q / math.sqrt(12)
B = {"B_eq": 4.6}


def _recording(folder, name, truth, *, amplitude=0.3, kp=40.0, kd=3.0, horizon=1.0, seed=1):
    """A P(D) step on ``truth`` as suite.make_case makes one, ``horizon`` seconds long."""
    pid = jc.PID(kp=kp, kd=kd, v_limit=6.0)
    rec = make_recording(build_plant(truth), pid, jc.step(amplitude, horizon=horizon), seed=seed)
    return read_experiment(write_recording(rec, folder / f"{name}.toml", force=True))


def _tap(folder, truth):
    rec = make_tap_recording(
        build_plant(truth, motor_connected=False), speed=0.6, rest=0.3, horizon=1.0, seed=2
    )
    path = write_recording(rec, folder / "tap.toml", force=True)
    text = path.read_text()
    if "[tap]" not in text:
        path.write_text(text + "\n[tap]\nmotor_connected = false\n")
    return read_experiment(path)


# ---------------------------------------------------------------- the rules, without a fit


def test_the_same_recording_twice_is_refused_not_taken_for_a_repeat():
    """Given twice, one run would look like a cart that repeats itself to 0 mm (and count its
    samples twice): refused before any fit, as ``jaxcart fit`` refuses it."""
    from jaxcart.errors import UserError

    rec = make_recording(jc.handout_plant(), jc.PID(kp=20.0), jc.step(0.1, horizon=0.5), seed=0)
    with pytest.raises(UserError, match="identical samples"):
        diagnose([rec, rec], progress=False)


def test_the_misfit_rule_and_widening_are_the_fits_own():
    assert MISFIT_RATIO == 3.0
    assert misfits(3.01 * FLOOR, FLOOR) and not misfits(3.0 * FLOOR, FLOOR)
    assert not misfits(math.nan, FLOOR)  # as fit has it: no number, no claim
    # max(robust, naive * sqrt(N / n_eff)), element by element.
    got = widened_for_model_error(np.array([1.0, 5.0]), np.array([4.0, 4.0]), 100, 25.0)
    np.testing.assert_allclose(got, [4.0, 5.0])


def test_a_run_whose_limit_does_not_act_is_left_out_of_the_runs_comparison():
    """Two P 50 runs held at 5.02 and 5.83 V (each under its 6 V command) beside a PI run that
    never sends 4.2 V, whose own limit the fit pushed to the top of its range (no standard
    error): the drive differs between the runs that reach their limits, and the PI run says
    nothing of its own. Before, its undefined standard error kept the drive per run out of the
    real cart's diagnosis once the students' Part (iv) PI run was added to its four recordings
    (docs/diagnose.md, "A run the diagnosis had not seen")."""
    values = {"v_sat@1": 5.02, "v_sat@2": 5.83, "v_sat@3": 30.0}
    peaks = {"command@1": 6.0, "command@2": 6.0, "command@3": 4.2}

    def stderr(w):
        return math.nan if "v_sat@3" in w else 0.05

    sig = significance((PER_RUN, "saturation"), values, stderr, peaks=peaks)
    assert not sig[PER_RUN]["why"] and sig[PER_RUN]["z"] == pytest.approx(0.81 / 0.05)
    # A run whose limit acts counts, determined or not.
    acting = {**values, "v_sat@3": 4.0}
    sig = significance((PER_RUN, "saturation"), acting, stderr, peaks=peaks)
    assert "standard error is not defined" in sig[PER_RUN]["why"]


def test_a_run_whose_limit_is_beyond_the_drives_spread_is_not_drawn_as_the_drive():
    """The independent cart whose drive limit differs per run (5.3 V, 6 % a run): the P 10
    step's limit fitted at 1.85 V, just under its 2 V peak (its drive gain read as a clipped
    peak), 2.9 times below what the P 50 runs drove. The cart's limit and a next run's draw
    come from the runs that agree (before, the draw took 1.85-5.35 V and the design band ran
    to infinity: docs/design.md); a limit above what its run drove (the ramp) says nothing.
    On the real cart the PD run's 0.68 A current limit is the only one that acts: kept."""
    values = {"v_sat@1": 5.02, "v_sat@2": 5.41, "v_sat@3": 1.85, "v_sat@4": 5.33, "v_sat@5": 9.0}
    peaks = {"command@1": 6.0, "command@2": 6.0, "command@3": 2.0, "command@4": 6.0,
             "command@5": 3.0}  # fmt: skip
    assert "run 4's v_sat is 2.9 times below" in per_run.per_run_inconsistency(values, peaks)
    assert per_run.drive_runs(values, peaks) == {"v_sat@1", "v_sat@2", "v_sat@4"}
    # A drive gain free per run is the drive's in every run.
    gains = {**values, "gamma_scale@3": 0.98}
    assert per_run.drive_runs(gains, peaks) == {"v_sat@1", "v_sat@2", "v_sat@4", "gamma_scale@3"}
    # Two acting runs, one of them low: nothing measures the spread without it; both kept.
    two = {"v_sat@1": 5.02, "v_sat@3": 1.85}
    assert per_run.drive_runs(two, peaks) == set(two)
    real = {"i_max@1": 3.0, "i_max@2": 3.0, "i_max@3": 0.68}
    currents = {"current@1": 2.3, "current@2": 1.5, "current@3": 1.4}
    assert per_run.drive_runs(real, currents) == {"i_max@3"}


def test_an_effect_at_its_bound_or_idle_is_not_named_and_its_z_is_reported():
    """A spring with k_s at its lower bound (y_rest off the track) is not named; f_c = 0.0005
    +/- 0.0005 N beside a saturation has its z reported (whether it is there is decided by
    held-out prediction, not by a Wald test); the drive limits free per run need z > 3."""
    spring = significance(("spring",), {"B_eq": 5.4, "k_s": 5e-4, "y_rest": 0.3}, lambda w: 0.00037)
    assert "lower bound" in spring["spring"]["why"]
    values = {"B_eq": 4.0, "v_sat": 4.0, "f_c": 0.000573}
    se = {"v_sat": 4.1e-5, "f_c": 0.00055}
    sig = significance(
        ("saturation", "coulomb"),
        values,
        lambda w: math.sqrt(sum((c * se[n]) ** 2 for n, c in w.items())),
        peaks={"command": 6.0},
    )
    assert sig["coulomb"]["z"] == pytest.approx(0.000573 / 0.00055)
    assert "too small to matter" in sig["coulomb"]["why"]  # under its least size worth naming
    runs = {"v_sat@1": 5.0, "v_sat@2": 5.1}
    same = significance((PER_RUN, "saturation"), runs, lambda w: 0.05, peaks={"command": 6.0})
    assert "standard errors from the same value in every run" in same[PER_RUN]["why"]
    assert sig["saturation"]["z"] == pytest.approx((6.0 - 4.0) / 4.1e-5)
    assert not sig["saturation"]["why"]
    # A limit above every command sent never acts.
    idle = significance(("saturation",), {"v_sat": 7.0}, lambda w: 0.01, peaks={"command": 6.0})
    assert idle["saturation"]["z"] < 0 and "does not act" in idle["saturation"]["why"]
    # Stiction is static friction above the kinetic level: the test is on f_s - f_c, with the
    # covariance of the two.
    cov = np.array([[1e-4, 0.9e-4], [0.9e-4, 1e-4]])

    def stderr(w):
        a = np.array([w.get("f_c", 0.0), w.get("f_s", 0.0)])
        return float(np.sqrt(a @ cov @ a))

    sig = significance(("stiction",), {"f_c": 0.3, "f_s": 0.32}, stderr)
    assert sig["stiction"]["z"] == pytest.approx(0.02 / math.sqrt(2e-4 - 1.8e-4))
    assert sig["coulomb"]["z"] > SIGNIFICANCE and not sig["coulomb"]["why"]
    # A correction must exceed CORRECTION_MARGIN of the start value by SIGNIFICANCE errors.
    start = {"M": 0.94, "gamma_scale": 1.0}
    tiny = significance(("mass",), {"M": 0.9402}, lambda w: 1e-5, start=start)
    assert "within 1%" in tiny["M"]["why"]
    real = significance(("mass",), {"M": 1.25}, lambda w: 1e-3, start=start)
    assert real["M"]["z"] == pytest.approx((0.31 - CORRECTION_MARGIN * 0.94) / 1e-3)


def test_a_part_at_its_neutral_bound_is_idle():
    """A part's own parameter at the bound on its neutral side makes the part idle (the search
    judges the structure without it); what it stands on is not idle on that account."""
    se = lambda w: 0.01  # noqa: E731
    fall = significance(("stribeck",), {"f_c": 0.4, "f_s": 0.6, "v_stribeck": 1e-4}, se)
    assert all(v["idle"] for v in fall.values()) and "lower bound" in fall["stribeck"]["why"]
    spring = significance(("spring",), {"k_s": 5e-4, "y_rest": 0.3}, se)
    assert spring["spring"]["idle"]
    # f_c at its lower bound inside Stribeck friction is Coulomb's, not the fall's own.
    low = significance(("stribeck",), {"f_c": 3e-5, "f_s": 0.6, "v_stribeck": 0.01}, se)
    assert not any(v["idle"] for v in low.values())


def test_implausible_values_are_flagged():
    """Values at the edge of a lab cart's range (the fits are held inside it) or at a fit's
    bound are flagged, and only those."""
    lines = implausible(
        {"B_eq": 0.3814, "v_sat": 4.48, "f_c": 0.37, "k_s": 5e-4, "y_rest": 1.13, "M": 1.2},
        ["B_eq", "v_sat", "f_c", "k_s", "y_rest", "M", "y0@0"],
    )
    text = "\n".join(lines)
    assert "B_eq = 0.3814 kg/s is outside" in text and f"{PLAUSIBLE['B_eq'][0]:.3g}" in text
    assert "k_s = 0.0005 N/m is outside what a cart of this lab has (0-200 N/m)" in text
    assert "y_rest = 1.13 m is outside what a cart of this lab has (-0.5-0.5 m)" in text
    assert not any(x.startswith(("v_sat", "f_c", "M ")) for x in lines)
    assert implausible({"B_eq": 4.0, "gamma_scale": 0.3}, ["B_eq", "gamma_scale"]) == [
        "gamma_scale = 0.3 is outside what a cart of this lab has (0.5-2): the data ask for "
        "a value beyond it"
    ]
    assert implausible({"B_eq": 5.0, "M": 1.2, "gamma_scale": 0.9}, ["B_eq", "M"]) == []


def test_m_and_gamma_scale_give_the_same_closed_loop():
    """The claim behind the tie: with B_eq free one closed loop fixes only gamma/m, c/m and
    every force over m. The mapped plant moves exactly as the corrected one."""
    from jaxcart.exact import simulate_exact
    from jaxcart.plantspec import build_plant

    base = jc.handout_plant()
    values = {"B_eq": 4.6, "M": 1.25, "v_sat": 4.0, "f_c": 0.3}
    parts, mapped = swapped_correction(("saturation", "coulomb", "mass"), values, base)
    assert parts == ("saturation", "coulomb", "gain") and "M" not in mapped
    pid = jc.PID(kp=40.0, kd=3.0, v_limit=6.0)
    exp = jc.step(0.4, horizon=1.0)
    a = simulate_exact(build_plant(values, base=base, check=False), pid, exp)
    b = simulate_exact(build_plant(mapped, base=base, check=False), pid, exp)
    np.testing.assert_allclose(a.position, b.position, atol=1e-9)
    back = swapped_correction(parts, mapped, base)[1]
    for k, v in values.items():
        assert back[k] == pytest.approx(v, rel=1e-12), k
    # No equivalent with a positive B_eq: the two differ (a cart has B_eq > 0).
    assert swapped_correction(("mass",), {"B_eq": 0.5, "M": 1.5}, base) is None


def test_forward_selection_extends_the_best_within_the_batch_slots():
    def single(name, free):
        return Candidate(name, (name,), ("B_eq", *free))

    sat, coul, dz, spring, stiction, mass = (
        single("saturation", ("v_sat",)),
        single("coulomb", ("f_c",)),
        single("deadzone", ("deadzone",)),
        single("spring", ("k_s", "y_rest")),
        single("stiction", ("f_c", "f_s")),
        Candidate("mass", ("mass",), ("B_eq", "M")),
    )
    pairs = [
        Candidate("saturation+coulomb", ("saturation", "coulomb"), ("B_eq", "v_sat", "f_c")),
        Candidate(
            "saturation+spring", ("saturation", "spring"), ("B_eq", "v_sat", "k_s", "y_rest")
        ),
    ]
    seen = {frozenset(c.parts) for c in pairs}
    additions = [coul, mass, stiction, spring, dz, sat]
    grown = extend(pairs, additions, seen, limit=4)
    names = [c.name for c, _, _ in grown]
    # The best seed with the best addition first; a seed's own part adds nothing.
    assert names[:2] == ["saturation+coulomb+mass", "saturation+spring+coulomb"]
    assert len(grown) == 4 and all(len(c.parts) == 3 for c, _, _ in grown)
    assert all(len(c.free) <= K_MAX for c, _, _ in grown)
    # Stiction holds Coulomb; saturation + spring + stiction has 6 free slots.
    assert not any({"coulomb", "stiction"} <= set(c.parts) for c, _, _ in grown)
    every = extend(pairs, additions, {frozenset(c.parts) for c in pairs}, limit=100)
    assert "saturation+spring+stiction" not in [c.name for c, _, _ in every]
    assert len({frozenset(c.parts) for c, _, _ in every}) == len(every)
    again = extend(pairs, additions, seen, limit=4)
    assert not {c.name for c, _, _ in again} & set(names)  # seen ones are not fitted again


def _diagnosis(**kw):
    base = dict(
        recordings=["run.toml"],
        status="diagnosed",
        messages=[],
        controller_checks=[],
        rms_before=1e-3,
        rms_after=2e-5,
        floor=FLOOR,
        chosen="saturation+mass",
        left_out=["saturation"],
        corrected_parameters=["M"],
        parameters={
            "B_eq": {"value": 4.6, "stderr": 1e-3, "unit": "kg/s"},
            "v_sat": {"value": 4.0, "stderr": 1e-4, "unit": "V"},
            "M": {"value": 1.25, "stderr": 1e-4, "unit": "kg"},
        },
        baseline={"B_eq": {"value": 7.0, "stderr": 0.1, "unit": "kg/s"}, "rms": 1e-3},
        start_values={"M": 0.94},
    )
    base.update(kw)
    return Diagnosis(**base)


def test_the_verdict_says_effects_and_corrections_and_what_it_does_not_know():
    d = _diagnosis()
    assert d.verdict == "left out: saturation; corrected parameters: M 0.94 -> 1.25 kg"
    d = _diagnosis(left_out=[], chosen="mass")
    assert d.verdict.startswith("corrected parameters: M 0.94 -> 1.25 kg; nothing left out")
    d = _diagnosis(
        rms_after=0.5e-3,
        explained=False,
        misfit="the best structure ... no candidate explains the recording",
        suggestions=["physics outside the effects library"],
        implausible=["B_eq = 0.38 kg/s is outside what a cart of this lab has (1.08-27 kg/s)"],
    )
    v = d.verdict
    assert v.startswith("not explained: the best approximation (left out:")
    assert f"ends at {0.5e-3 / FLOOR:.0f} times the encoder floor" in v  # 76 times
    assert "at 3.2 times" in _diagnosis(explained=False, rms_after=3.2 * FLOOR).verdict
    assert "corrected parameters: M 0.94 -> 1.25 kg" in v
    assert "what may be missing: physics outside the effects library" in v
    assert "implausible: B_eq = 0.38 kg/s" in v
    doc = d.to_json()
    assert doc["explained"] is False and doc["floor_ratio"] == pytest.approx(0.5e-3 / FLOOR)
    assert doc["suggestions"] and doc["implausible"] and doc["misfit"]
    title = figure_title(d)
    assert title.startswith("NOT EXPLAINED") and "implausible: B_eq = 0.38 kg/s" in title
    narrow = figure_title(d, 30)  # at most three lines, a cut said by an ellipsis
    assert len(narrow.splitlines()) == 3 and narrow.endswith(" ...")
    md = render_markdown(d)
    assert "## Not explained" in md and "## Implausible values" in md


# ---------------------------------------------------------------- diagnoses


def test_a_controller_reading_counts_is_simulated_reading_them(tmp_path):
    """The hardware's controller reads whole counts. Its recorded command shows it (the replay
    on the counts gives it to 0 V), and the diagnosis's simulation reads them too: the
    baseline ends at the floor. Fed the exact position it sat at 1.7-2.1 x the floor, a model
    error that a structure which is not there absorbed (a spring at its bound, a 0.02 %
    heavier cart). Nothing is named."""
    rec = _recording(tmp_path, "null", {**B, "quantization": Q})
    d = diagnose([rec], progress=False)
    assert d.controller_checks[0]["reads_counts"]
    assert d.rms_before / d.floor < 1.3, d.rms_before / d.floor
    assert d.left_out == [] and d.corrected_parameters == [] and d.explained
    assert d.verdict.startswith("nothing left out")
    assert d.parameters["B_eq"]["value"] == pytest.approx(4.6, rel=0.01)


def test_friction_under_integral_action_with_the_counts_in_the_loop(tmp_path):
    """A PID reading whole counts holds the cart against 0.15 N of Coulomb friction, hunting
    between counts. With the exact position fed back the diagnosis named 0.07 N of friction
    and a 0.05 V deadzone (2 s recording); reading the counts as the controller did, it finds
    the friction alone, to 2 %, at the floor."""
    pid = jc.PID(kp=40.0, kd=3.0, ki=20.0, v_limit=6.0)
    truth = build_plant({**B, "f_c": 0.15, "quantization": Q})
    rec = make_recording(truth, pid, jc.step(0.3, horizon=1.0), seed=1)
    rec = read_experiment(write_recording(rec, tmp_path / "pi.toml", force=True))
    d = diagnose([rec], progress=False)
    assert d.left_out == ["coulomb"] and d.corrected_parameters == [], d.verdict
    assert d.parameters["f_c"]["value"] == pytest.approx(0.15, rel=0.02)
    assert d.parameters["B_eq"]["value"] == pytest.approx(4.6, rel=0.01)
    assert d.explained and d.floor_ratio < 1.3


def test_noisy_data_that_are_not_counts_are_judged_against_their_noise(tmp_path):
    """No encoder grid, 20 um of white noise: the floor is the noise (fit's floor_of), and the
    right model explains the recording (with a 1e-7 m floor it was "not explained", 201x)."""
    pid = jc.PID(kp=40.0, kd=3.0, v_limit=6.0)
    rec = make_recording(
        build_plant(B), pid, jc.step(0.3, horizon=1.0), quantization=0.0, noise=2e-5, seed=3
    )
    rec = read_experiment(write_recording(rec, tmp_path / "noisy.toml", force=True))
    d = diagnose([rec], progress=False)
    assert d.floor == pytest.approx(2e-5, rel=0.1)  # the noise, measured from the data
    assert d.explained and d.left_out == [] and d.corrected_parameters == [], d.verdict
    assert d.parameters["B_eq"]["value"] == pytest.approx(4.6, rel=0.02)


def test_an_insignificant_second_effect_or_correction_is_not_named(tmp_path):
    """A 3 ms delay, the controller reading counts: the old diagnosis named the delay with a
    Coulomb friction of 0.8 mN (+/- 1.5 mN) on a 2 s recording, or (unsaid) a 0.04 % heavier
    cart on this 1 s one."""
    rec = _recording(tmp_path, "delay", {**B, "delay": 0.003, "quantization": Q}, kp=60.0, kd=4.0)
    d = diagnose([rec], progress=False)
    assert d.left_out == ["delay"] and d.corrected_parameters == [], d.verdict
    assert d.parameters["delay"]["value"] == pytest.approx(0.003, rel=0.01)
    assert d.significance["delay"] > SIGNIFICANCE
    for c in d.candidates:  # every structure with an effect or correction was tested
        if c.parts:
            assert c.assessed is not None and set(c.z) >= set(c.effects)


def test_a_recording_no_candidate_explains_says_so(tmp_path):
    """Friction that varies along the track (track_friction is no candidate): the best
    structure ends far above the floor. The verdict says no candidate explains it, names the
    best approximation and how far it is, suggests what may be missing, and the standard errors
    are widened for model error as jaxcart fit widens its own."""
    rec = _recording(tmp_path, "track", {**B, "f_track": TRACK_WAVE}, amplitude=0.4)
    d = diagnose([rec], progress=False)
    assert not d.explained and d.floor_ratio > MISFIT_RATIO
    assert d.verdict.startswith("not explained: the best approximation")
    assert " times its encoder floor" in d.verdict and "fitted to" in d.verdict
    assert any("along the track" in s for s in d.suggestions)  # its residual follows position
    assert "physics outside the effects library" in d.suggestions
    # The standard errors: the fit's widening of the robust ones.
    best = next(c for c in d.candidates if c.name == d.chosen)
    segs = [prepare(rec, min_coasting=MIN_COASTING)]
    names = list(best.free)
    jac = best.jac / fitter_scale(segs)
    plain = covariance(segs, names, best.values, jac, best.residuals)
    n = sum(r.size for r in best.residuals)
    n_eff = effective_samples(best.residuals)
    for k in names:
        p = d.parameters[k]
        assert p["stderr_widened"]
        i = names.index(k)
        want = widened_for_model_error(plain.stderr({k: 1.0}), plain.naive[i, i], n, n_eff)
        assert p["stderr"] == pytest.approx(float(want), rel=1e-9)
    # The robust sandwich's Newey-West lags absorb part of this slow model error (the engine's
    # covariance, shared with jaxcart fit); what the residual's n_eff supports is still larger.
    assert d.parameters["B_eq"]["stderr"] > 1.5 * plain.stderr({"B_eq": 1.0})
    doc = d.to_json()
    assert doc["explained"] is False and doc["misfit"] and doc["suggestions"]
    assert "## Not explained" in render_markdown(d) and figure_title(d).startswith("NOT EXPLAINED")


def test_forward_selection_finds_three_parts_and_says_effects_and_correction(tmp_path):
    """Saturation, Coulomb friction and a heavier cart: no pair reaches the floor (the old
    diagnosis ended at 45 times it, naming saturation alone), round 3 extends the best pairs by
    one, the chosen structure reaches the floor and the verdict says the effects, the
    correction, and that M and gamma_scale cannot be told apart (B_eq not settled)."""
    truth = {**B, "v_sat": 4.0, "f_c": 0.3, "M": 1.25}
    rec = _recording(tmp_path, "sat_coul_m", truth, amplitude=0.4)
    d = diagnose([rec], progress=False)
    assert set(d.left_out) == {"saturation", "coulomb"}, d.verdict
    assert d.rms_after < 2.5 * d.floor
    assert any(c.round >= 3 and len(c.parts) == 3 for c in d.candidates)
    assert max(c.round for c in d.candidates if isinstance(c.round, int)) <= 4  # it stops
    assert "left out: saturation, coulomb; corrected parameters: " in d.verdict
    corrected = d.corrected_parameters[0]
    assert corrected in ("M", "gamma_scale")
    u = d.unidentifiable
    assert u and "cannot be told apart" in d.verdict and "diagnose a tap" in d.verdict
    assert d.parameters["B_eq"]["settled"] is False
    assert u["B_eq"][0] < truth["B_eq"] * 1.01 and u["B_eq"][1] > truth["B_eq"] * 0.99
    m = build_plant(truth)
    assert u["ratios"]["gamma/m"] == pytest.approx(float(m.gamma / m.m), rel=1e-3)
    assert u["ratios"]["c/m"] == pytest.approx(float(m.c / m.m), rel=1e-3)
    mass = next(a for a in u["alternatives"] if "M" in a["values"])
    assert mass["values"]["M"] == pytest.approx(1.25, rel=0.01)


def test_of_m_and_gamma_scale_the_plausible_one_is_named(tmp_path):
    """A heavier cart (M = 1.31 kg, B_eq = 4 kg/s) on one closed loop: the weaker motor fits
    it as well but needs B_eq = 0.99 kg/s, which no cart of this lab has; the heavier cart is
    named, the tie said."""
    rec = _recording(tmp_path, "heavy", {"B_eq": 4.0, "M": 1.31})
    d = diagnose([rec], progress=False)
    assert d.corrected_parameters == ["M"] and d.left_out == [], d.verdict
    assert d.parameters["M"]["value"] == pytest.approx(1.31, rel=0.01)
    assert d.parameters["B_eq"]["value"] == pytest.approx(4.0, rel=0.02)
    assert d.unidentifiable and not d.implausible


def test_a_tap_of_the_same_cart_separates_m_and_gamma_scale(tmp_path):
    """The suggestion holds: jointly with a tap (motor unplugged: B_eq / m alone), the closed
    loop's gamma/m and c/m fix M and B_eq; no tie is left. (The closed loop alone ties.)"""
    truth = {**B, "M": 1.25}
    recs = [_recording(tmp_path, "heavy", truth), _tap(tmp_path, truth)]
    d = diagnose(recs, progress=False)
    assert d.left_out == [] and d.corrected_parameters == ["M"], d.verdict
    assert not d.unidentifiable and "cannot be told apart" not in d.verdict
    assert d.parameters["M"]["value"] == pytest.approx(1.25, rel=0.01)
    assert d.parameters["B_eq"]["value"] == pytest.approx(4.6, rel=0.01)
    assert "settled" not in d.parameters["B_eq"]


def test_a_drive_gain_beside_a_tap_is_named_on_an_independent_generators_cart(tmp_path):
    """A drive 1.5 % weak (gamma_scale 0.985) under Coulomb friction, a PD step and a tap from
    the independent generator (what real recordings carry): the tap tells the gain from a mass
    change, and the gain is found with Coulomb friction. (Only the mass was paired with the
    round's leads: "not explained", 1.13 mm left, a helper's own simulator found it.)"""
    from tuning.verification import REALISTIC, TrueCart
    from tuning.verification import experiments as ex
    from tuning.verification import make_recording as make_independent

    values = {"B_eq": 5.5, "f_c": 0.6, "gamma_scale": 0.985}
    art = REALISTIC.replace(gain_spread=0.0, limit_spread=0.0)
    runs = [
        (TrueCart.from_values(values), ex.step(jc.PID(kp=55.0, kd=5.0), 0.3, horizon=1.0)),
        (TrueCart.from_values(values, motor_connected=False), ex.tap(speed=0.6, horizon=1.0)),
    ]
    paths = [
        make_independent(truth, e, tmp_path / f"run{i}.toml", art, seed=i + 1).path
        for i, (truth, e) in enumerate(runs)
    ]
    d = diagnose([read_experiment(p) for p in paths], progress=False)
    # (Held out to 0.027 mm, 4 times the floor: the generator's drive wanders as a real one
    # does, which no structure follows.)
    assert d.corrected_parameters == ["gamma_scale"] and d.left_out == ["coulomb"], d.verdict
    assert d.parameters["gamma_scale"]["value"] == pytest.approx(0.985, abs=0.002)
    assert d.parameters["B_eq"]["value"] == pytest.approx(5.5, rel=0.02)
    assert d.parameters["f_c"]["value"] == pytest.approx(0.6, rel=0.03)


def test_the_drives_gain_per_run_is_there_where_the_runs_differ():
    """The gain free per run (Search.gain_per_run's structure): each run's own gamma_scale, and
    its limits; never grown by the forward selection. Gains 1.0003 and 1.0057 (the independent
    cart with a 12 ms lag), each within 1 % of the start plant's 1, are there because they
    differ by 0.0054, 10.8 standard errors of 0.0005 (the Wald test of PER_RUN's limits);
    gains 1.0003 and 1.0008 are not (1 standard error)."""
    c = structure(("saturation", "coulomb", "gain", PER_RUN), (1, 2))
    assert {"gamma_scale@1", "gamma_scale@2", "v_sat@1", "v_sat@2"} <= set(c.free)
    assert "gamma_scale" not in c.free
    sat = structure(("saturation", PER_RUN), (1, 2))
    gain = structure(("gain",))
    assert extend([sat], [gain], set()) == []  # only from a structure the search reached
    # Nor paired with it in round 2 (where a tap lets the gain be paired: the real tap, P 50
    # runs and PD run stopped the lab on the batch's missing gamma_scale@k slots).
    assert not batchable(("saturation", PER_RUN, "gain"))
    assert batchable(("saturation", PER_RUN, "mass")) and batchable(("coulomb", "gain"))
    assert not batchable(("coulomb", "mass", "gain"))
    assert swapped_correction(c.parts, {}, None) is None  # each run's gain is its own
    values = {"B_eq": 1.5, "gamma_scale@1": 1.0003, "gamma_scale@2": 1.0057}
    sig = significance(
        ("gain", PER_RUN), values, lambda w: 0.0005 * math.hypot(*w.values()) / 2**0.5
    )
    assert not sig["gamma_scale"]["why"] and sig["gamma_scale"]["z"] == pytest.approx(10.8)
    assert not sig[PER_RUN]["why"]
    values["gamma_scale@2"] = 1.0008
    sig = significance(
        ("gain", PER_RUN), values, lambda w: 0.0005 * math.hypot(*w.values()) / 2**0.5
    )
    assert sig["gamma_scale"]["why"] and sig[PER_RUN]["why"]
