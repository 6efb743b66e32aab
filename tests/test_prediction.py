"""The prediction of a design on the cart as measured (tuning.design.uncertainty,
tuning.design.prediction) and a run checked against it (hw.predicted): the band's coverage on
synthetic carts, the draws' statistics, the drive's spread, the plant file's round trip, and a
run outside its band explained by the value that moved."""

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import norm
from scipy.stats import t as student_t

import jaxcart as jc
from hw.predicted import FAR, FAR_T, check_lines, check_run, far
from jaxcart.plantspec import build_plant, read_plant_file, write_plant_file
from tuning.design.losses import Spec
from tuning.design.prediction import Prediction, band_of, predict, step_run, t_factor
from tuning.design.uncertainty import CartUncertainty, fit_table, from_fit, from_fit_table

#: The coverage test's design and step: a PID on a cart with Coulomb friction and the drive's
#: 6 V, a 0.2 m step over 1.5 s (short runs: the test makes 800 of them).
PID = jc.PID(kp=100.0, kd=5.0, ki=2.0, v_limit=6.0)
STEP = jc.step(0.2, horizon=1.5)
#: The fit's standard errors of B_eq [kg/s] and f_c [N] in the coverage test.
SE = np.array([0.25, 0.04])


def _cart(b_eq, f_c):
    return build_plant({"B_eq": b_eq, "f_c": f_c, "v_sat": 6.0})


def test_band_is_the_order_statistics_of_a_prediction_interval():
    """n = 19 at 90 %: the least and the most (a new draw inside with probability 18/20);
    n = 63: the 3rd least and 3rd most (60/64)."""
    x = np.arange(19.0)[::-1]
    assert band_of(x, 0.9) == (0.0, 18.0)
    assert band_of(np.arange(63.0), 0.9) == (2.0, 60.0)


@pytest.fixture(scope="module")
def coverage():
    """40 synthetic carts: each true cart drawn from a lab's range, its fit off by an error
    drawn from the fit's covariance, the design's band predicted from that fit (19 carts:
    a 90 % band of the least and the most) and the true cart's step beside it (seeded)."""
    rng = np.random.default_rng(30)
    inside = {"settling_time": [], "overshoot": [], "position": []}
    for _ in range(40):
        truth = np.array([rng.uniform(2.0, 5.0), rng.uniform(0.2, 0.5)])
        fitted = truth + SE * rng.standard_normal(2)
        u = CartUncertainty(_cart(*fitted), ("B_eq", "f_c"), fitted, np.diag(SE**2))
        p = predict(u, PID, experiment=STEP, n=19, seed=int(rng.integers(1 << 30)),
                    sensitivity=False)  # fmt: skip
        y, _, metrics = step_run((_cart(*truth), PID, STEP))
        for name in ("settling_time", "overshoot"):
            lo, hi = p.interval(name)
            inside[name].append(lo <= metrics[name] <= hi)
        k = int(0.25 / 1e-3)  # mid-motion, 0.25 s into the step
        inside["position"].append(p.band[0][k] <= y[k] <= p.band[1][k])
    return {k: float(np.mean(v)) for k, v in inside.items()}


@pytest.mark.parametrize("what", ["settling_time", "overshoot", "position"])
def test_the_truth_lies_in_the_90_percent_band_about_90_percent_of_the_time(coverage, what):
    """The band's coverage on synthetic carts, the exact simulator for the truth and for the
    drawn carts: about 90 % (40 carts: 0.9 +/- 0.05 is one binomial standard deviation; the
    band of 19 draws covers with probability 0.9 where the fit's error is as its covariance
    says). Measured (seed 30): settling 0.9, overshoot 0.875, position 0.9."""
    assert 0.8 <= coverage[what] <= 0.975, coverage


def test_draws_have_the_fits_mean_and_covariance():
    """Shared values from the normal distribution of the fit (correlations included), each
    drive value as a new run's: the runs' mean, their spread times sqrt(1 + 1/n) times
    Student's t with n - 1 degrees of freedom, with the standard error of the mean."""
    cov = np.array([[0.04, -0.006], [-0.006, 0.0025]])
    runs = (5.1, 5.9, 5.4)
    u = CartUncertainty(
        _cart(3.0, 0.4), ("B_eq", "f_c"), np.array([3.0, 0.4]), cov,
        {"v_sat": runs}, {"v_sat": (0.03, 0.02, 0.02)},
    )  # fmt: skip
    draws = u.draw(20000, seed=1)
    x = np.array([[d["B_eq"], d["f_c"]] for d in draws])
    assert np.allclose(x.mean(axis=0), [3.0, 0.4], atol=0.01)
    assert np.allclose(np.cov(x.T), cov, rtol=0.05, atol=1e-5)
    v = np.array([d["v_sat"] for d in draws])
    mean, scale = np.mean(runs), np.std(runs, ddof=1) * math.sqrt(4 / 3)
    se_mean = math.sqrt(0.03**2 + 2 * 0.02**2) / 3
    assert u.drive_spread("v_sat") == pytest.approx((mean, math.hypot(scale, se_mean)))
    # The t with 2 degrees of freedom (the fits' own errors, 1/20 of the spread, aside):
    # its 5 % and 95 % points are 2.92 scales from the mean, a normal's 1.645.
    q = np.quantile(v, [0.05, 0.95])
    edges = mean + np.array([-1, 1]) * student_t.ppf(0.95, 2) * scale
    assert q == pytest.approx(edges, abs=0.25 * scale)  # (a normal's: 1.27 scales nearer)
    assert u.stderr("v_sat") == pytest.approx(math.hypot(scale, se_mean))
    # The tuner's training carts: a normal of the same scale, whose worst of a dozen is not
    # a t's one-in-twenty tail.
    normal = np.array([d["v_sat"] for d in u.draw(20000, seed=1, tails=False)])
    assert normal.std() == pytest.approx(u.stderr("v_sat"), rel=0.03)
    assert u.stderr("f_c") == pytest.approx(0.05)
    wide = u.scaled(2.0)
    assert wide.stderr("B_eq") == pytest.approx(0.4)
    assert wide.stderr("v_sat") == pytest.approx(2 * u.stderr("v_sat"))


@pytest.mark.parametrize("n", [2, 3, 5])
@pytest.mark.parametrize("tails", [True, False])
def test_a_new_runs_drive_lies_in_the_90_percent_band_of_the_draws_90_percent_of_the_time(n, tails):
    """A drive value measured in n runs (normal about a value the runs do not know, with a
    spread they do not know either): the 5-95 % band of carts drawn from them holds a new
    run's value about 90 % of the time (600 trials: 0.9 +/- 0.012 is one binomial standard
    deviation): the t, 88, 90 and 89 %. A normal draw of the same scale (``tails`` False, the
    tuner's training carts) holds it less, the fewer the runs: 63, 74 and 83 % (in theory 66,
    76 and 83 %)."""
    rng = np.random.default_rng(n)
    inside = []
    for _ in range(600):
        runs = 5.0 + 0.2 * rng.standard_normal(n + 1)
        u = CartUncertainty(_cart(3.0, 0.4), (), np.zeros(0), np.zeros((0, 0)),
                            {"v_sat": tuple(runs[:n])})  # fmt: skip
        drawn = [d["v_sat"] for d in u.draw(199, seed=int(rng.integers(1 << 30)), tails=tails)]
        lo, hi = np.quantile(drawn, [0.05, 0.95])
        inside.append(lo <= runs[n] <= hi)
    if tails:
        assert 0.86 <= np.mean(inside) <= 0.94, np.mean(inside)
    else:
        assert abs(np.mean(inside) - {2: 0.66, 3: 0.76, 5: 0.83}[n]) < 0.04, np.mean(inside)


def test_uncertainty_from_a_fit_and_through_a_plant_file(tmp_path):
    """A fit's shared values with standard errors and correlations, its values per run as the
    drive's spread; a plant file's [fit] table keeps both (jaxcart tune --plant ... --robust
    reads them back)."""
    est = {
        "B_eq": SimpleNamespace(value=1.5, stderr=0.02),
        "f_c": SimpleNamespace(value=0.43, stderr=0.008),
        "delay": SimpleNamespace(value=0.012, stderr=None),  # no standard error: not drawn
        "v_sat@0": SimpleNamespace(value=5.09, stderr=0.03),
        "v_sat@2": SimpleNamespace(value=5.90, stderr=0.02),
    }
    plant = build_plant({"B_eq": 1.5, "f_c": 0.43, "delay": 0.012, "v_sat": 5.09})
    fit = SimpleNamespace(params=est, correlation={("B_eq", "f_c"): -0.5})
    u = from_fit(fit, plant=plant)
    assert u.names == ("B_eq", "f_c") and u.drive == {"v_sat": (5.09, 5.90)}
    assert u.cov[0, 1] == pytest.approx(-0.5 * 0.02 * 0.008)
    path = write_plant_file(tmp_path / "cart.toml", plant, fit={"source": "test", **fit_table(u)})
    back = from_fit_table(*read_plant_file(path))
    assert back.names == u.names and back.drive == u.drive
    assert [back.stderr(n) for n in back.varied] == pytest.approx([u.stderr(n) for n in u.varied])
    assert from_fit_table(plant, {"source": "no errors"}) is None


def test_a_run_outside_its_band_is_explained_by_the_value_that_moved():
    """A design predicted on a cart whose drive limit varies from run to run (eight runs: a t
    with 7 degrees of freedom); the run on a cart whose limit is 3.5 spreads lower settles
    later, outside the band (0.896 s, the band's edge 0.887 s), and the check names v_sat,
    3.9 spreads lower by its linear sensitivity (within the t's 4.53; a fitted value's 3
    standard errors would not have named it), the other values barely moving the settling
    time."""
    runs = (5.0, 5.2, 5.4, 5.1, 5.3, 5.2, 5.25, 5.15)
    u = CartUncertainty(
        _cart(3.0, 0.4), ("B_eq", "f_c"), np.array([3.0, 0.4]), np.diag([0.05, 0.01]) ** 2,
        {"v_sat": runs}, {"v_sat": (0.01,) * len(runs)},
    )  # fmt: skip
    pid = jc.PID(kp=80.0, kd=6.0, v_limit=6.0)
    exp = jc.step(0.5, horizon=2.0)
    p = predict(u, pid, experiment=exp, n=19, seed=3)
    doc = p.to_json()
    assert doc["metrics"]["settling_time"]["nominal"] == pytest.approx(p.nominal["settling_time"])
    assert doc["sensitivity"]["v_sat"]["settling_time"] < 0  # a stronger drive settles sooner
    assert doc["sensitivity"]["v_sat"]["dof"] == 7 and "dof" not in doc["sensitivity"]["B_eq"]
    spread = u.stderr("v_sat")
    _, _, run = step_run((u.cart({"v_sat": np.mean(runs) - 3.5 * spread}), pid, exp))
    check = check_run(run, doc)
    assert not check["inside"]
    best = check["outside"][0]["explained_by"][0]
    assert best["name"] == "v_sat" and -4.53 < best["sigmas"] < -3.0
    assert any("v_sat" in line and "spread lower" in line for line in check_lines(check))
    _, _, same = step_run((u.nominal_cart(), pid, exp))
    assert check_run(same, doc)["inside"]


def test_how_far_a_drive_value_may_move_is_the_ts_point_of_a_normals_three_sigma():
    """hw/predicted's table (the lab PC has no scipy) against scipy.stats: the t's two-sided
    0.27 % point for 1-30 degrees of freedom, to its two decimals; FAR beyond and without."""
    assert FAR == pytest.approx(norm.ppf(1 - 0.00135), abs=0.01)
    for dof, value in enumerate(FAR_T, start=1):
        assert value == pytest.approx(student_t.ppf(1 - 0.00135, dof), abs=0.006), dof
        assert far({"dof": float(dof)}) == value
    assert far({}) == far({"dof": 31}) == far({"dof": "x"}) == FAR


def test_a_drive_value_from_two_runs_explains_as_far_as_its_t_reaches():
    """A drive value drawn from two runs (Student's t, 1 degree of freedom) may lie 8 of its
    scales out about one run in thirteen (2 atan(1/8) / pi): a run 0.4 s late, where it moves
    the settling by -0.05 s a scale, is explained by it; a fitted value (no "dof") 8 standard
    errors out is not, nor a drive value moved through zero."""
    entry = {"stderr": 0.3, "value": 5.5, "unit": "V", "settling_time": -0.05}
    band = {"settling_time": {"nominal": 0.8, "band": [0.75, 0.85]}}
    prediction = {"level": 0.9, "metrics": band, "sensitivity": {"v_sat": {**entry, "dof": 1}}}
    check = check_run({"settling_time": 1.2}, prediction)
    assert check["outside"][0]["explained_by"][0]["sigmas"] == pytest.approx(-8.0)
    prediction["sensitivity"]["v_sat"] = entry
    assert check_run({"settling_time": 1.2}, prediction)["outside"][0]["explained_by"] == []
    prediction["sensitivity"]["v_sat"] = {**entry, "dof": 1}
    assert check_run({"settling_time": 2.0}, prediction)["outside"][0]["explained_by"] == []


def test_check_says_when_no_single_value_explains_a_run():
    prediction = {
        "level": 0.9,
        "metrics": {"overshoot": {"nominal": 1.0, "band": [0.5, 1.5]}},
        "sensitivity": {"B_eq": {"stderr": 0.1, "value": 2.0, "unit": "kg/s", "overshoot": 0.1}},
    }
    check = check_run({"overshoot": 9.0}, prediction)  # 80 standard errors of B_eq
    assert check["outside"][0]["explained_by"] == []
    assert "leaves out" in check_lines(check)[-1]


def test_the_model_error_bounds_a_new_runs_miss_from_the_recorded_steps():
    """tuning.design.calibration: a first-order step 0.5 (1 - exp(-t/0.1)) enters its 2 % band
    at 0.1 ln 50 = 0.391 s (to the 1 ms sample); a run's time miss is the larger of its
    entering and settling misses, a settling miss only where the recording settles within the
    design's 3 s horizon (a PI run creeping to 7.24 s against 7.59 s simulated counts by its
    entering miss, 3 ms); the model error is Student's t bound on a new run's miss at the
    band's 90 %: t_{0.95, n} times the runs' RMS miss (scipy.stats.t: 2.920 for n = 2, checked
    against the table value)."""
    from tuning.design.calibration import StepMiss, entering, miss_bound, model_error

    t = np.arange(0.0, 2.0, 1e-3)
    y = 0.5 * (1.0 - np.exp(-t / 0.1))
    assert entering(t, y, np.full_like(t, 0.5)) == pytest.approx(0.1 * math.log(50.0), abs=1e-3)
    assert entering(t, 0.2 * y, np.full_like(t, 0.5)) == math.inf
    p50 = StepMiss("p50.toml", (0.573, 0.560), (0.939, 0.920), (5.8, 5.5))
    pi = StepMiss("pi.toml", (0.772, 0.769), (7.238, 7.592), (33.5, 33.3))
    p10 = StepMiss("p10.toml", (math.inf, math.inf), (math.inf, math.inf), (0.0, 0.0))
    assert pi.time == pytest.approx(0.003) and p50.time == pytest.approx(0.019)
    assert math.isnan(p10.time)
    error = model_error([p50, pi, p10])
    assert error["settling_time"] == pytest.approx(
        2.920 * math.sqrt((0.019**2 + 0.003**2) / 2), 1e-3
    )
    assert error["overshoot"] == pytest.approx(2.353 * math.sqrt((0.3**2 + 0.2**2) / 3), 1e-3)
    assert error["steps"] == {"settling_time": 2, "overshoot": 3}
    assert model_error([]) == {
        "settling_time": 0.0, "overshoot": 0.0, "steps": {"settling_time": 0, "overshoot": 0}
    }  # fmt: skip
    # The table's t_{0.95, n}: one step's miss alone is multiplied by 6.314.
    assert t_factor(1) == pytest.approx(6.314, abs=1e-3)
    assert t_factor(3) == pytest.approx(2.353, abs=1e-3)
    # Of three runs' misses, a new one is past their largest a quarter of the time; the bound
    # holds a new normal miss 90 % of the time.
    rng = np.random.default_rng(0)
    draws = rng.standard_normal((20000, 4))
    bounds = np.array([miss_bound(np.abs(d[:3])) for d in draws])
    assert np.mean(np.abs(draws[:, 3]) <= bounds) == pytest.approx(0.90, abs=0.01)
    assert np.mean(np.abs(draws[:, 3]) <= np.abs(draws[:, :3]).max(axis=1)) == pytest.approx(
        0.75, abs=0.01
    )


def test_no_band_edge_falls_below_zero():
    """A model error larger than the fit's band (the one recorded step of a PD run, missed by
    216 ms, gives 1.36 s) widens every metric's band upwards in full and downwards to 0 at
    most: a settling time, an overshoot, a peak command and an excursion are never negative."""
    t = np.arange(0.0, 1.0, 1e-3)
    metrics = {"settling_time": np.full(63, 0.88), "overshoot": np.full(63, 1.2),
               "peak_voltage": np.full(63, 6.0), "excursion": np.full(63, 0.5)}  # fmt: skip
    p = Prediction(
        None, Spec(), 0.9, t, np.full(t.size, 0.5), t, t, {}, (t, t), metrics,
        np.ones(63, dtype=bool),
        model_error={"settling_time": 1.36, "overshoot": 2.0},
    )  # fmt: skip
    assert p.interval("settling_time") == pytest.approx((0.0, 0.88 + 1.36))
    assert p.interval("overshoot") == pytest.approx((0.0, 3.2))
    assert p.interval("peak_voltage") == pytest.approx((6.0, 6.0))


def test_the_chance_of_meeting_the_spec_carries_the_models_miss():
    """P(spec): without a model error, the share of the drawn carts that meet the spec; with
    one, each cart's chance that a new run's miss (Student's t, as many degrees of freedom as
    recorded steps, scaled to the bound) keeps it inside: a cart at 0.88 s with one step's
    bound of 1.364 s meets a 1 s spec with t_1's probability of 0.12 / 0.216 (0.66, from
    scipy.stats.t); a cart past the command's range never does."""
    from scipy.stats import t as student_t

    t = np.arange(0.0, 1.0, 1e-3)
    settling = np.array([0.88, 0.88, 1.2, 0.5])
    metrics = {"settling_time": settling, "overshoot": np.array([1.0, 1.0, 1.0, 1.0]),
               "peak_voltage": np.array([6.0, 6.0, 6.0, 7.0]),
               "excursion": np.full(4, 0.5)}  # fmt: skip
    meets = np.array([True, True, False, False])
    p = Prediction(None, Spec(), 0.9, t, t, t, t, {}, (t, t), metrics, meets)
    assert p.p_meet == pytest.approx(0.5)
    bound = 0.216 * t_factor(1)
    steps = {"settling_time": 1, "overshoot": 4}
    error = {"settling_time": bound, "overshoot": 0.0, "steps": steps}
    p = dataclasses.replace(p, model_error=error)
    want = (2 * student_t.cdf(0.12 / 0.216, 1) + student_t.cdf(-0.2 / 0.216, 1)) / 4
    assert p.p_meet == pytest.approx(want, rel=1e-12)
    assert 0.3 < p.p_meet < 0.5


def test_a_recorded_step_is_predicted_by_the_cart_fitted_without_it():
    """tuning.lab.part_v_design.own_cart: a step the joint fit held out is predicted by that
    fold's cart (its shared values fitted to the other recordings, its own drive limit to it
    alone); one not held out by the fitted cart with its own drive limit; the others' limits
    never enter."""
    from tuning.estimation.fit import Estimate
    from tuning.lab.part_v_design import held_values, own_cart

    plant = build_plant({"B_eq": 2.0, "f_c": 0.4, "v_sat": 5.5})
    u = CartUncertainty(
        plant, ("B_eq", "f_c"), np.array([2.0, 0.4]), np.diag([0.02, 0.01]) ** 2,
        drive={"v_sat": [5.0, 6.0]},
    )  # fmt: skip
    fold = {"B_eq": 2.3, "f_c": 0.35, "v_sat@1": 5.2, "v_sat@2": 9.9, "y0@0": 0.1}
    params = {
        "B_eq": Estimate("B_eq", 2.0, 0.02), "f_c": Estimate("f_c", 0.4, 0.01),
        "v_sat@1": Estimate("v_sat@1", 5.0, 0.01), "v_sat@2": Estimate("v_sat@2", 6.0, 0.01),
    }  # fmt: skip
    segments = [SimpleNamespace(held_out=None), SimpleNamespace(held_out=fold)]
    segments.append(SimpleNamespace(held_out=None))
    joint = SimpleNamespace(
        uncertainty=u,
        names=("tap.toml", "p50.toml", "pd.toml"),
        fit=SimpleNamespace(params=params, segments=segments),
    )
    p50, pd = (SimpleNamespace(path=Path(n)) for n in ("p50.toml", "pd.toml"))
    assert held_values(joint, p50) is fold and held_values(joint, pd) is None
    fitted, held = own_cart(joint, p50), own_cart(joint, p50, held_out=True)

    def of(cart, names=("B_eq", "f_c", "v_sat")):
        return tuple(float(cart.get(n)) for n in names)

    assert of(fitted) == pytest.approx((2.0, 0.4, 5.0))
    assert of(held) == pytest.approx((2.3, 0.35, 5.2))
    other = own_cart(joint, pd, held_out=True)  # not held out: the fit, its own limit
    assert of(other) == pytest.approx((2.0, 0.4, 6.0))


def test_a_value_the_recordings_disagree_on_is_drawn_from_its_held_out_spread():
    """tuning.design.uncertainty.held_out_spread is the jackknife's standard error: for the
    mean of n numbers, whose fits without each number are the means of the rest, it is the
    textbook s / sqrt(n) (to rounding). from_fit widens a standard error to that spread where
    the spread is larger (the correlation kept), says so, and leaves the others."""
    from tuning.design.uncertainty import held_out_spread
    from tuning.estimation.fit import Estimate

    z = np.random.default_rng(3).normal(1.2, 0.05, 6)
    rest = [np.delete(z, i).mean() for i in range(z.size)]
    segments = [SimpleNamespace(held_out={"i_max": r, "B_eq": 2.5 + 1e-5 * i}) for i, r in
                enumerate(rest)]  # fmt: skip
    spread = held_out_spread(("i_max", "B_eq", "f_c"), segments)
    assert spread[0] == pytest.approx(np.std(z, ddof=1) / math.sqrt(z.size), rel=1e-12)
    assert spread[2] == 0.0  # no fold has it
    assert held_out_spread(("i_max",), segments[:2])[0] == 0.0  # too few folds
    fit = SimpleNamespace(
        params={"i_max": Estimate("i_max", 1.2, 0.003), "B_eq": Estimate("B_eq", 2.5, 0.01)},
        segments=[*segments, SimpleNamespace(held_out=None)],
        correlation={("i_max", "B_eq"): 0.5},
    )
    u = from_fit(fit, plant=build_plant({"B_eq": 2.5, "i_max": 1.2}))
    assert u.stderr("i_max") == pytest.approx(spread[0]) and u.stderr("B_eq") == 0.01
    assert u.widened == {"i_max": (0.003, pytest.approx(spread[0]))}
    assert u.cov[0, 1] == pytest.approx(0.5 * spread[0] * 0.01)
