"""jaxcart diagnose: the fast subset of the concealed-effect suite
(tuning/estimation/diagnose/suite.py),
bad input, and the command line. The whole suite: ``python -m tuning.estimation.diagnose.suite``."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

import jaxcart as jc
from jaxcart.errors import UserError
from jaxcart.files import read_experiment
from jaxcart.plantspec import build_plant
from jaxcart.synthetic import make_recording, write_recording
from tuning.estimation.diagnose import diagnose, render_markdown, write_outputs
from tuning.estimation.diagnose.suite import CASES, FAST, judge, make_case
from tuning.estimation.fitting.result import FitResult

BY_NAME = {c.name: c for c in CASES}


@pytest.fixture(scope="module")
def fast_results(tmp_path_factory):
    folder = tmp_path_factory.mktemp("suite")
    out = {}
    for name in FAST:
        case = BY_NAME[name]
        paths = make_case(case, folder)
        d = diagnose([read_experiment(path) for path in paths], progress=False)
        out[name] = (case, d)
    return out


@pytest.mark.parametrize("name", FAST)
def test_fast_suite_names_the_truth(fast_results, name):
    case, d = fast_results[name]
    row = judge(case, d)
    assert row["correct"], row
    assert not row["false_alarm"], row
    assert d.rms_after <= d.rms_before * 1.0001
    if case.expect or case.rule == "corrected":
        assert d.rms_after < 2.5 * d.floor  # down to the encoder's quantization
        assert row["ratio"] > 10


def test_fast_suite_says_what_one_recording_cannot_tell(fast_results):
    """A heavier cart on one closed loop: M and gamma_scale tie (only gamma/m and c/m are
    identifiable), said in the verdict, B_eq not settled. Every fast case but the one no
    candidate explains is explained, and none needs the forward selection past pairs
    (docs/diagnose.md)."""
    _, d = fast_results["heavier cart (M)"]
    assert not d.left_out and d.corrected_parameters in (["M"], ["gamma_scale"])
    assert d.unidentifiable and "cannot be told apart" in d.verdict
    assert d.parameters["B_eq"]["settled"] is False
    for name, (case, d) in fast_results.items():
        assert d.explained == (case.rule != "not_explained") and not d.implausible, name
        assert max(c.round for c in d.candidates) <= 2, name


def _judged(case, **fields):
    """judge() of a made-up diagnosis of ``case`` (no fit): its fields as given."""
    from tuning.estimation.diagnose.result import Diagnosis
    from tuning.estimation.diagnose.structures import Candidate

    parts = fields.pop("parts", ())
    d = Diagnosis(["a"], "diagnosed", [], [], rms_before=1e-3, rms_after=1e-5, **fields)
    d.candidates = [Candidate("+".join(parts), tuple(parts), ("B_eq",))]
    d.chosen = d.candidates[0].name
    return judge(case, d)


def test_the_suite_judges_each_case_by_its_rule():
    """What counts as right: a spurious deadzone beside Coulomb friction under PI fails the
    "exact" rule; the drive freed per run is right only with each run's own limit near its
    truth (5 %) and none for the tap, and a false alarm where the runs share one limit; a
    recording no candidate explains is right only said so, with the suggestion; static
    friction that falls over a 2 mm/s Stribeck speed (the independent generator's) is named
    rightly as Coulomb + stiction or as Stribeck friction, and on exact data (no fall) only as
    the first."""
    from tuning.estimation.diagnose.structures import PER_RUN

    pi = BY_NAME["coulomb under PI on a lab cart (no deadzone)"]
    assert pi.rule == "exact"
    assert _judged(pi, left_out=["coulomb"])["correct"]
    assert not _judged(pi, left_out=["coulomb", "deadzone"], equivalent=[["coulomb"]])["correct"]
    per_run = BY_NAME["tap + P and PD steps with the drive limit per run"]
    parts = ("coulomb", "saturation", PER_RUN)
    own = {
        f"run {i}": {"parameters": {} if v is None else {"v_sat": {"value": v}}}
        for i, v in enumerate((None, 4.6 * 1.03, 5.5 * 0.98))
    }
    row = _judged(per_run, left_out=["coulomb", "saturation"], parts=parts, per_recording=own)
    assert row["correct"] and not row["false_alarm"] and PER_RUN in row["named"]
    own["run 2"]["parameters"]["v_sat"]["value"] = 4.6  # the first run's limit: wrong
    row = _judged(per_run, left_out=["coulomb", "saturation"], parts=parts, per_recording=own)
    assert not row["correct"]
    shared = BY_NAME["tap + two P steps with one drive limit"]
    row = _judged(shared, left_out=["coulomb", "saturation"], parts=parts, per_recording=own)
    assert not row["correct"] and row["false_alarm"]
    assert _judged(shared, left_out=["coulomb", "saturation"], parts=parts[:2])["correct"]
    track = BY_NAME["track friction (no candidate)"]
    along = ["a force that varies along the track (...)"]
    assert _judged(track, explained=False, suggestions=along)["correct"]
    assert not _judged(track, explained=True, suggestions=along)["correct"]
    assert not _judged(track, explained=False, suggestions=["more effects at once"])["correct"]
    hunting = BY_NAME["strong stiction hunting under PI"]
    stribeck = ["coulomb", "stiction", "stribeck"]
    assert _judged(hunting.on("independent"), left_out=stribeck)["correct"]
    assert _judged(hunting.on("independent"), left_out=stribeck[:2])["correct"]
    assert not _judged(hunting, left_out=stribeck)["correct"]
    clean = BY_NAME["clean PD step"]
    assert _judged(clean)["correct"]
    row = _judged(clean, left_out=["spring"])
    assert not row["correct"] and row["false_alarm"]
    _judges_the_curve_along_the_track()


def _judges_the_curve_along_the_track():
    """Rule "curve" where the truth's friction varies along the track: the position's curve
    named and within 0.05 N of the truth (0.2 N, +0.4 N from +0.2 m on, linear from -0.2 m)
    at the knots it fitted; the speed's curve named there is wrong, and the position's named
    on a cart without it a false alarm."""
    along = BY_NAME["one cart (steps and out-and-back both ways): friction along the track"]
    # The truth's friction at -0.2, 0 and 0.2 m is 0.2, 0.4 and 0.6 N.
    read = {"positions": [-0.2, 0.0, 0.2], "levels": [0.21, 0.44, 0.6]}
    track = {"named": True, "curve": read}
    row = _judged(along, explained=False, friction_curve={"track": track})
    assert row["correct"] and not row["false_alarm"] and "track curve" in row["named"]
    off = {**track, "curve": {**read, "levels": [0.21, 0.46, 0.6]}}
    assert not _judged(along, explained=False, friction_curve={"track": off})["correct"]
    speed = {"named": True, "curve": {"speeds": [], "levels": {}, "bands": {}}}
    assert not _judged(along, explained=False, friction_curve=speed)["correct"]
    rise = BY_NAME["one cart (taps both ways): friction rising with speed"]
    row = _judged(rise, explained=False, friction_curve={"track": track})
    assert not row["correct"] and row["false_alarm"]


def test_a_case_of_several_runs_is_one_cart(tmp_path):
    """The runs of a case share the case's truth, each with its own changes (the drive limit),
    each written as its own experiment file; the tap with the motor unplugged."""
    case = BY_NAME["tap + P and PD steps with the drive limit per run"]
    runs = case.recordings()
    assert [r.kind for r in runs] == ["tap", "step", "step"]
    assert [r.truth.get("v_sat") for r in runs] == [None, 4.6, 5.5]
    assert all(r.truth["B_eq"] == 1.5 and r.truth["f_c"] == 0.4 for r in runs)
    recs = [read_experiment(p) for p in make_case(case, tmp_path)]
    assert [r.kind for r in recs] == ["tap", "closed_loop", "closed_loop"]
    assert recs[0].meta["tap"]["motor_connected"] is False
    assert recs[2].controller.kd == 2.0 and recs[1].controller.kd == 0.0
    # The drive limits differ: the P run's command is clipped by the software at 6 V, the
    # cart's motion by the amplifier at 4.6 V (the truth), not seen in the command.
    assert max(abs(recs[1].command)) == pytest.approx(6.0)


def test_json_and_outputs(fast_results, tmp_path):
    _, d = fast_results["coulomb plain"]
    assert abs(d.parameters["f_c"]["value"] - 0.4) < 0.01
    assert d.parameters["f_c"]["stderr"] > 0
    written = write_outputs(d, tmp_path / "out", json_path=tmp_path / "d.json")
    data = json.loads((tmp_path / "d.json").read_text())
    for key in (
        "left_out",
        "rms_before",
        "rms_after",
        "parameters",
        "windows",
        "candidates",
        "plant_file",
    ):
        assert key in data
    assert data["left_out"] == ["coulomb"]
    assert all("rms" in c and "score" in c for c in data["candidates"])
    assert all(c["fit"]["params"]["B_eq"]["stderr"] > 0 for c in data["candidates"])
    plant = jc.read_plant_file(written["plant_file"])[0]
    assert "coulomb" in plant.structure
    assert "Diagnosis" in render_markdown(d)
    with pytest.raises(UserError, match="exists"):
        write_outputs(d, tmp_path / "out")


def test_every_candidate_holds_its_fit_and_the_chosen_one_is_the_diagnosis_fit(fast_results):
    """One result type: each structure tried holds its fit as ``jaxcart fit`` reports one
    (values with standard errors, each recording's exact runs, the fitted cart); the named
    one's is ``Diagnosis.fit``, whose values are those the verdict gives."""
    _, d = fast_results["coulomb plain"]
    for c in d.candidates:
        assert isinstance(c.result, FitResult), c.name
        assert set(c.result.params) <= set(c.values), c.name
        for n, e in c.result.params.items():
            assert e.value == pytest.approx(c.values[n]) and e.stderr >= 0, (c.name, n)
        after = np.concatenate([s.after_exact - s.measured for s in c.result.segments])
        assert np.sqrt(np.mean(after**2)) == pytest.approx(c.rms_exact, rel=1e-9), c.name
    chosen = next(c for c in d.candidates if c.name == d.chosen)
    assert d.fit is chosen.result
    assert d.fit.params["f_c"].value == pytest.approx(d.parameters["f_c"]["value"])
    assert d.fit.params["f_c"].stderr == pytest.approx(d.parameters["f_c"]["stderr"])
    assert abs(d.fit.params["f_c"].value - 0.4) < 0.01  # the truth
    assert "coulomb" in d.fit.cart.structure
    assert all(
        "+/-" in line for line in render_markdown(d).splitlines() if line.startswith("| coulomb |")
    )


def test_no_excitation_is_not_diagnosed():
    rec = make_recording(jc.handout_plant(), jc.PID(kp=40.0), jc.step(0.0001, horizon=1.0))
    d = diagnose([rec], progress=False)
    assert d.status == "not diagnosed"
    assert "excitation" in d.messages[0]
    short = make_recording(jc.handout_plant(), jc.PID(kp=40.0), jc.step(0.3, horizon=0.05))
    d = diagnose([short], progress=False)
    assert d.status == "not diagnosed" and "too short" in d.messages[0]


def test_controller_mismatch_is_reported_and_inferred(tmp_path):
    from tuning.estimation.diagnose.controller import check

    ran = jc.PID(kp=30.0, kd=2.0, tau=0.005, v_limit=6.0)
    rec = make_recording(jc.handout_plant(B_eq=4.6), ran, jc.step(0.3, horizon=1.0))
    path = write_recording(rec, tmp_path / "run.toml")
    text = path.read_text().replace("kp = 30", "kp = 50")
    path.write_text(text)
    chk = check(read_experiment(path))
    assert not chk["consistent"]
    inf = chk["inferred"]
    # The synthetic controller saw the exact position, the regression sees whole counts: the
    # derivative of counts biases kd and tau a little.
    assert abs(inf.kp - 30.0) < 1.0 and abs(inf.kd - 2.0) < 0.25
    assert chk["inferred_rms"] < 0.1 * chk["mismatch_rms"]
    assert inf.derivative_on == "error" and inf.v_limit == pytest.approx(6.0)


def test_the_replay_tells_whether_the_controller_read_the_counts(tmp_path):
    """A controller reading the encoder (the ``quantization`` sensor in the truth) computed its
    command from exactly the recorded counts: the replay gives it to 0 V. One fed the exact
    position misses by about kp q / sqrt(12) or more: 40 V/m x 6.6 um = 0.26 mV in the P term,
    the derivative of the counts adding more. The threshold is a tenth of the P term's."""
    from tuning.estimation.diagnose.controller import check, reads_counts

    q = 2.275e-5
    pid = jc.PID(kp=40.0, kd=3.0, ki=20.0, v_limit=6.0)
    exp = jc.step(0.3, horizon=1.0)
    truth = {"B_eq": 4.6, "f_c": 0.15}
    in_loop = make_recording(build_plant({**truth, "quantization": q}), pid, exp, seed=1)
    exact_fed = make_recording(build_plant(truth), pid, exp, seed=1)
    a = check(read_experiment(write_recording(in_loop, tmp_path / "counts.toml")))
    b = check(read_experiment(write_recording(exact_fed, tmp_path / "exact.toml")))
    assert a["consistent"] and a["mismatch_rms"] == 0.0 and a["reads_counts"]
    assert "it read the recorded encoder counts" in a["message"]
    assert b["consistent"] and not b["reads_counts"]
    assert b["mismatch_rms"] > 40.0 * q / math.sqrt(12)  # at least the P term's
    assert "encoder counts" not in b["message"]
    # The rule itself: data that are not counts never read counts.
    assert reads_counts(40.0, 0.0, q) and not reads_counts(40.0, 0.0, 0.0)
    assert not reads_counts(40.0, 0.2 * 40.0 * q / math.sqrt(12), q)


def test_a_truth_reading_its_encoder_records_what_it_read():
    """The synthetic encoder keeps a position that is already a whole count as that count
    (y / q may round to just below it): every recorded value is what the controller read."""
    from jaxcart.synthetic import Encoder

    q = 2.275e-5
    counts = np.arange(-20000, 20000)
    y = counts * q  # what a controller reading the encoder saw, in floats
    assert np.array_equal(np.round(Encoder(q, seed=0).read(y) / q), counts)
    # Positions within a count still floor: the encoder's quantization is unchanged.
    inside = (counts + 0.5) * q
    assert np.array_equal(np.round(Encoder(q, seed=0).read(inside) / q), counts)


def test_cli_help_is_instant_and_refuses_overwrite(tmp_path):
    code = (
        "import sys; from tuning.commands.main import build_parser; build_parser(); "
        "print('jax' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "False"
    (tmp_path / "report.md").write_text("x")
    from tuning.commands.main import main

    rec = make_recording(jc.handout_plant(), jc.PID(kp=40.0), jc.step(0.3, horizon=0.5))
    path = write_recording(rec, tmp_path / "r.toml")
    assert main(["diagnose", str(path), "--out", str(tmp_path), "--quiet"]) == 2
    assert (tmp_path / "report.md").read_text() == "x"
    assert np.isfinite(rec.position).all()


def test_every_registered_effect_is_a_candidate_or_says_why_not():
    from jaxcart.effects import REGISTRY
    from tuning.estimation.diagnose.structures import effect_params, not_candidates

    EFFECT_PARAMS, NOT_CANDIDATES = effect_params(), not_candidates()

    for name in REGISTRY:
        assert (name in EFFECT_PARAMS) != (name in NOT_CANDIDATES), name
    for name, params in EFFECT_PARAMS.items():
        assert set(params) >= set(REGISTRY[name].param_names()), name


def test_an_effect_along_the_track_is_a_candidate_only_where_the_recordings_cover_it(
    monkeypatch,
):
    """An effect that declares ``covers`` (a map along the track) is searched only where the
    recordings span that much of the track; without the span it is left out."""
    from jaxcart.effects import REGISTRY
    from tuning.estimation.engine import parameters

    monkeypatch.setattr(REGISTRY["spring"], "covers", 0.4)
    assert "spring" not in parameters.candidates() and "spring" not in parameters.candidates(
        span=0.3
    )
    assert parameters.candidates(span=0.5)["spring"] == ("k_s", "y_rest")
    covers = [n for n, cls in REGISTRY.items() if cls.covers and n != "spring"]
    assert covers == ["track_friction"] and "0.4 m" in REGISTRY["track_friction"].not_candidate


def test_exact_memo_reuses_runs_read_only_and_keeps_the_newest():
    """The diagnosis's memo of exact runs: the same structure and values give the stored run
    (not a new one), read-only; another value or structure is a new run; the oldest goes."""
    from types import SimpleNamespace

    from tuning.estimation.engine.exact_runs import ExactMemo

    memo, runs = ExactMemo(size=2), []

    def compute():
        runs.append(1)
        return [np.zeros(3)], [None]

    a = SimpleNamespace(parts=("coulomb",), corrections=())
    b = SimpleNamespace(parts=("spring",), corrections=())
    first = memo.get(a, {"B_eq": 4.6, "f_c": 0.45}, compute)
    assert memo.get(a, {"f_c": 0.45, "B_eq": 4.6}, compute) is first and len(runs) == 1
    assert not first[0][0].flags.writeable
    memo.get(a, {"B_eq": 4.6, "f_c": 0.4500000001}, compute)
    memo.get(b, {"B_eq": 4.6, "f_c": 0.45}, compute)
    assert len(runs) == 3 and memo.hits == 1
    memo.get(a, {"B_eq": 4.6, "f_c": 0.45}, compute)  # evicted: run again
    assert len(runs) == 4


def test_exact_memo_reruns_only_the_recordings_a_value_moves(tmp_path):
    """A joint diagnosis's exact runs are kept per recording: a drive limit free per run moves
    its own run alone (the other runs and the unplugged tap are the stored ones), a shared
    value moves every run, and the residuals made in this process without the memo equal
    those made several at a time, in a helper process (jaxcart.workers), bit for bit."""
    from jaxcart.workers import Helpers
    from tuning.estimation.diagnose import candidate_runs, structures
    from tuning.estimation.diagnose.search import Search
    from tuning.estimation.engine import exact_runs, parameters

    case = BY_NAME["tap + P and PD steps with the drive limit per run"]
    recs = [read_experiment(p) for p in make_case(case, tmp_path)]
    search = Search(recs, [None] * 3, [False] * 3, None, lambda line: None, None)
    cand = next(c for c in search.round1 if structures.PER_RUN in c.parts)
    values = dict(search.starts_all)
    values = {k: values.get(k, values.get(parameters.base_name(k))) for k in cand.free}
    with Helpers(1) as helpers:
        memo = exact_runs.ExactMemo(executor=helpers)
        args = (cand, search.segments, search.base_plants)
        first, _ = candidate_runs.exact_residuals(*args, values, search.layout, memo)
        assert memo.made == 3
        own = next(k for k in cand.free if k.endswith("@2"))
        moved = dict(values, **{own: values[own] * 1.01})
        before = set(memo.one)
        r, _ = candidate_runs.exact_residuals(*args, moved, search.layout, memo)
        assert memo.made == 4 and [key[0] for key in set(memo.one) - before] == [2]
        assert r[0] is first[0] and r[1] is first[1] and r[2] is not first[2]
        fresh, _ = candidate_runs.exact_residuals(*args, moved, search.layout)  # (no memo: here)
        assert all(np.array_equal(a, b) for a, b in zip(r, fresh, strict=True))
        candidate_runs.exact_residuals(
            *args, dict(values, B_eq=values["B_eq"] * 1.01), search.layout, memo
        )
        assert memo.made == 7


def test_an_effect_is_a_candidate_only_where_the_recordings_can_show_it():
    """A difference between the directions needs the cart sliding both ways, the lesser at
    least a fifth of the greater (a step's overshoot of a few mm in 0.4 m shows none); a dead
    band by direction needs the drive pushing both ways; a tilt needs a tap (in a driven run
    it is a drive offset)."""
    from jaxcart.effects import REGISTRY
    from tuning.estimation.diagnose.structures import candidate_list
    from tuning.estimation.engine.coverage import Coverage

    step = Coverage(span=0.4, right=0.40, left=0.008, push_right=6.0, push_left=1.7, driven=True)
    out_back = Coverage(span=0.4, right=0.30, left=0.43, push_right=6.0, push_left=6.0, driven=True)
    assert not step.shows("both_ways") and out_back.shows("both_ways")
    assert "slides both ways" in step.lacks(REGISTRY["coulomb_asymmetry"])
    assert step.lacks(REGISTRY["deadzone_asymmetry"]) == ""
    assert "a tap" in out_back.lacks(REGISTRY["tilt"])
    names = {c.name for c in candidate_list(True, (), step)}
    assert {"coulomb_asymmetry", "viscous_asymmetry", "tilt"}.isdisjoint(names)
    assert {"coulomb", "deadzone_asymmetry", "voltage_offset"} <= names
    both = {c.name for c in candidate_list(True, (), out_back)}
    assert {"coulomb_asymmetry", "viscous_asymmetry"} <= both


def test_a_part_fitted_to_where_it_does_nothing_leaves_the_structure_it_led_to(tmp_path):
    """The independent generator's Coulomb friction by direction, on a reference out and back:
    with M free (fitted within 1 % of the start plant's, a correction one would not name,
    absorbing what its recording carries and no candidate models: the amplifier's 0.1 ms lag)
    Coulomb by direction fits best by far; a dead band by direction fits better only while M
    is held. The structure named is the best one without its idle part, with the truth's
    values (0.3 N and 0.1 N either way), not the dead band."""
    from tuning.estimation.diagnose.search import _idle_parts
    from tuning.estimation.diagnose.suite import make_recordings

    sig = {
        "coulomb": {"why": "", "idle": False, "part": "coulomb"},
        "M": {"why": "M = 0.9416 is within ...", "idle": True, "part": "mass"},
    }
    assert _idle_parts(("coulomb", "mass"), sig) == ("mass",)
    sig["coulomb"] = {"why": "f_c sits at its lower bound", "idle": False, "part": "coulomb"}
    assert _idle_parts(("coulomb", "mass"), sig) == ()  # dropping M would not make it eligible

    case = BY_NAME["coulomb by direction"].on("independent")
    made = make_recordings(case, tmp_path, "independent")
    d = diagnose([read_experiment(p) for p, _ in made], progress=False)
    row = judge(case, d, [truth for _, truth in made])
    assert row["correct"] and not row["false_alarm"], row
    values = {k: v["value"] for k, v in d.parameters.items()}
    assert values["f_c"] == pytest.approx(0.3, abs=0.015)
    assert values["f_c_asym"] == pytest.approx(0.1, abs=0.01)


def test_structures_that_run_along_one_path_tie(tmp_path):
    """The independent generator's 0.4 V dead band under a P step whose command never falls
    below the band: a dead band and a drive offset of -0.4 V are one model on it (their exact
    runs lie within the criterion's floor of each other, 0.0026 mm against 0.0099 mm, though
    the offset scores lower), so whichever is named, the other is said to fit equally well,
    and the offset's value is the band's."""
    from tuning.estimation.diagnose.suite import make_recordings

    case = BY_NAME["deadzone plain"].on("independent")
    made = make_recordings(case, tmp_path, "independent")
    d = diagnose([read_experiment(p) for p, _ in made], progress=False)
    row = judge(case, d, [truth for _, truth in made])
    assert row["correct"], row
    named = set(d.left_out)
    tied = [set(e) for e in d.equivalent]
    assert {"deadzone"} in [named, *tied] and {"voltage_offset"} in [named, *tied], row
    if "v_offset" in d.parameters:
        assert d.parameters["v_offset"]["value"] == pytest.approx(-0.4, abs=0.01)


def test_the_suite_judges_a_friction_curve():
    """Rule "curve": the curve named and within 0.05 N of the truth's friction at 80 and 320
    mm/s; a curve named where the truth's friction does not vary with the speed (a dead band)
    is a false alarm, and so is one named on a clean case."""
    rising = BY_NAME["one cart (taps both ways): friction rising with speed"]
    truth = {"B_eq": 4.6, "f_c": 0.3, "rise_pos": 0.3, "rise_neg": 0.15, "v_rise": 0.03}
    speeds = (0.0, 0.005, 0.02, 0.08, 0.32)
    right, left = [0.3, 0.3, 0.45, 0.58, 0.6], [0.3, 0.3, 0.37, 0.44, 0.45]
    bands = {"right": [0.01] * 5, "left": [0.01] * 5}

    def curve(named, levels):
        c = {"speeds": speeds, "levels": dict(zip(("right", "left"), levels, strict=True))}
        c["bands"] = bands
        return {"named": named, "curve": c, "sides": ("right", "left")}

    row = judge(rising, _diagnosis(friction_curve=curve(True, (right, left))), [truth])
    assert row["correct"] and not row["false_alarm"] and "speed curve" in row["named"]
    wrong = (right, [0.3, 0.3, 0.37, 0.55, 0.56])  # 0.11 N too high moving left
    assert not judge(rising, _diagnosis(friction_curve=curve(True, wrong)), [truth])["correct"]
    assert not judge(rising, _diagnosis(friction_curve=curve(False, (right, left))), [truth])[
        "correct"
    ]
    dead_band = BY_NAME["one cart (tap + P 50 + PI): deadzone 0.3 V"]
    row = judge(dead_band, _diagnosis(friction_curve=curve(True, (right, left))), [{"f_c": 0.4}])
    assert row["false_alarm"]
    clean = BY_NAME["clean PD step"]
    assert judge(clean, _diagnosis(friction_curve=curve(True, (right, left))))["false_alarm"]


def _diagnosis(**fields):
    from tuning.estimation.diagnose.result import Diagnosis

    return Diagnosis(["a"], "diagnosed", [], [], rms_before=1e-3, rms_after=1e-5, **fields)
