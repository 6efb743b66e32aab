"""The lab's classic analyses (tuning/estimation/classic.py) against the truth of synthetic
recordings made
by the exact simulator, and on the real recordings."""

import math
import os

import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.errors import UserError
from jaxcart.synthetic import make_recording, make_tap_recording
from tuning.estimation.classic import loglinear_beq, pcontrol_fc_bounds, ramp_breakaway_fc

P50 = jc.PID(kp=50.0, v_limit=6.0)


def test_loglinear_beq_viscous_tap_matches_truth():
    # Viscous friction only: v = v0 exp(-B_eq t / m) exactly, so the method is unbiased; the
    # encoder's counts leave a scatter of ln|v| that the least-squares line averages out.
    for b_eq in (2.0, 5.4):
        rec = make_tap_recording(jc.tap_plant(B_eq=b_eq), speed=1.0, rest=0.3, seed=3)
        est = loglinear_beq(rec)
        assert est.name == "B_eq"
        assert est.value == pytest.approx(b_eq, rel=5e-3)
        assert est.stderr < 0.01 * b_eq
        assert 0.3 < est.details["start_time"] < 0.5  # after the push (rest 0.3 s + 0.1 s)
        assert "log-linear" in est.method


def test_loglinear_beq_overestimates_with_coulomb_friction():
    # The handout's method leaves Coulomb friction out; its constant deceleration steepens the
    # log-velocity line, so B_eq comes out too large (the documented bias of the method).
    truth = jc.tap_plant(B_eq=2.5, effects=(jc.Coulomb(f_c=0.5),))
    est = loglinear_beq(make_tap_recording(truth, seed=0))
    assert est.value > 1.1 * 2.5


def test_ramp_breakaway_fc_is_slightly_high():
    # gamma u at breakaway equals the static friction exactly; the cart is seen moving a few
    # counts late, when the ramp has climbed a little further: high by a few percent.
    f_c = 0.5
    plant = jc.handout_plant(f_c=f_c)
    rec = make_recording(plant, None, jc.voltage_ramp(0.1, horizon=4.0), seed=2)
    est = ramp_breakaway_fc(rec)
    true_breakaway = f_c / float(plant.gamma)  # [V], reached at t = 10 * that [s]
    assert est.details["voltage"] > true_breakaway
    assert est.value == pytest.approx(f_c, rel=0.08)
    assert est.value > f_c


def test_pcontrol_bounds_bracket_the_truth():
    f_c = 0.5
    plant = jc.handout_plant(f_c=f_c, B_eq=2.5)
    rec = make_recording(plant, P50, jc.step(0.4, horizon=1.5), seed=1)
    est = pcontrol_fc_bounds(rec)
    assert est.value is None
    assert est.lower <= f_c < est.upper
    # Independent check of the lower bound: kp gamma |e| at the true (unquantized) rest.
    e_true = 0.4 - rec.true_position[-1]
    assert est.lower == pytest.approx(50.0 * float(plant.gamma) * abs(e_true), abs=0.01)


def test_pcontrol_bounds_on_positions_with_white_noise():
    # No encoder, 20 um of white noise (a cart read by another sensor): the cart at rest
    # scatters by several IP02 counts, which is neither motion nor reversals.
    f_c = 0.38
    plant = jc.handout_plant(f_c=f_c, B_eq=3.2)
    rec = make_recording(
        plant, P50, jc.step(0.4, horizon=3.0), quantization=0.0, noise=20e-6, seed=1
    )
    est = pcontrol_fc_bounds(rec)
    assert est.lower <= f_c < est.upper


def test_classic_methods_refuse_the_wrong_recording():
    tap = make_recording(jc.tap_plant(B_eq=3.0), None, jc.tap(1.0, horizon=0.5), seed=0)
    with pytest.raises(UserError, match="open_loop"):
        ramp_breakaway_fc(tap)
    with pytest.raises(UserError, match="closed_loop"):
        pcontrol_fc_bounds(tap)
    pi = make_recording(
        jc.handout_plant(f_c=0.3), jc.PID(kp=50.0, ki=5.0, v_limit=6.0), jc.step(0.1), seed=0
    )
    with pytest.raises(UserError, match="ki = 0"):
        pcontrol_fc_bounds(pi)
    with pytest.raises(UserError, match="tap"):
        loglinear_beq(pi)
    still = make_recording(jc.handout_plant(f_c=2.0), None, jc.voltage_ramp(0.1, horizon=2.0))
    with pytest.raises(UserError, match="never moves"):
        ramp_breakaway_fc(still)


def test_pcontrol_bounds_need_a_cart_at_rest():
    # Cut the recording while the cart still moves: no steady state to read.
    rec = make_recording(jc.handout_plant(f_c=0.5), P50, jc.step(0.4, horizon=0.5), seed=0)
    with pytest.raises(UserError, match="still moves"):
        pcontrol_fc_bounds(rec)


def test_real_recordings(realdata):
    from jaxcart.files import read_experiment

    tap = read_experiment(os.path.join(realdata, "tap.toml"))
    est = loglinear_beq(tap)
    assert 3.1 < est.details["start_time"] < 3.5
    assert 0.5 < est.value < 10.0 and math.isfinite(est.stderr)
    p50 = read_experiment(os.path.join(realdata, "p50.toml"))
    bounds = pcontrol_fc_bounds(p50)
    # The cart stops about 3 mm short of 0.4 m (README): kp gamma |e| with the handout's gamma.
    gamma = float(jc.handout_plant().gamma)
    assert bounds.details["e_inf"] == pytest.approx(0.003, abs=3e-4)
    assert bounds.lower == pytest.approx(50.0 * gamma * abs(bounds.details["e_inf"]), rel=1e-9)
    assert bounds.upper is not None and bounds.lower < bounds.upper


def test_ramp_breakaway_uses_the_recorded_command():
    # A recording whose column v differs from the experiment's input: the command counts.
    plant = jc.handout_plant(f_c=0.5)
    rec = make_recording(plant, None, jc.voltage_ramp(0.1, horizon=4.0), seed=0)
    doubled = rec.__class__(**{**rec.__dict__, "command": 2 * np.asarray(rec.command)})
    est = ramp_breakaway_fc(doubled)
    assert est.details["voltage"] == pytest.approx(2 * ramp_breakaway_fc(rec).details["voltage"])
    assert jnp.asarray(rec.experiment.signal).shape == rec.position.shape
