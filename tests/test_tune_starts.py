"""The tuner's batch of starts (tuning/design/problem.py: starts, model_start): the given start,
the pole-placement design for the plant, then perturbations of the given start.

Nothing here runs the tuner's compiled iteration: the starts are numbers, checked against the
textbook's second-order design recomputed here from the closed loop's own poles.
"""

import math

import numpy as np
import pytest

import jaxcart as jc
from hw.control_law import PID
from tuning.design.losses import PARAM_NAMES, LossSettings, Spec
from tuning.design.problem import ZERO_START, model_start, starts, tuning_problem


def problem(plant=None, *, free=("kp", "kd", "ki"), spec=None, controller=None, start=None):
    return tuning_problem(
        plant,
        spec=spec or Spec(),
        start=start,
        free=free,
        controller=controller,
        robust=False,
        bounds=None,
        settings=LossSettings(),
        substeps=None,
        n_check=0,
        seed=0,
    )


def damping_and_frequency(plant, kp, kd):
    """(zeta, omega_n) of the closed loop m s^2 + (c + gamma kd) s + gamma kp, from its poles."""
    m, c, gamma = float(plant.m), float(plant.c), float(plant.gamma)
    poles = np.roots([m, c + gamma * kd, gamma * kp])
    omega = float(np.abs(poles[0]))
    return -float(poles[0].real) / omega, omega


def test_the_design_has_the_damping_of_the_overshoot_and_settles_at_the_bound():
    # A cart with little damping of its own (motor unplugged): kd > 0 places both poles.
    plant = jc.Plant(motor_connected=False)
    spec = Spec(settling_time=1.0, overshoot=5.0)
    designed = model_start(problem(plant, spec=spec))
    kp, kd = designed[0], designed[1]
    zeta, omega = damping_and_frequency(plant, kp, kd)
    shoot = 0.05
    assert zeta == pytest.approx(-math.log(shoot) / math.hypot(math.pi, math.log(shoot)))
    # The envelope enters the 2 % band at the settling bound.
    assert math.exp(-zeta * omega * 1.0) / math.sqrt(1 - zeta**2) == pytest.approx(spec.band)
    # Every other parameter is the given start's (the handout's ki; the template's tau ...).
    assert designed[2] == 5.0
    assert list(designed[3:]) == [0.01, 1.0, 6.0]


def test_a_cart_damped_more_than_the_design_starts_kd_where_a_zero_start_would():
    # The handout plant's back-EMF damping alone exceeds the design's: kd <= 0 asked for.
    designed = model_start(problem())
    assert designed[1] == ZERO_START["kd"]
    plant = jc.handout_plant()
    omega = math.sqrt(float(plant.gamma) * designed[0] / float(plant.m))
    assert omega > 0 and designed[0] < 600.0  # inside the box


def test_the_batch_is_the_given_start_the_design_then_perturbations():
    p = problem()
    theta, _ = starts(p, 4, 0.5, 0)
    theta = np.asarray(theta)
    free = p.free_mask
    assert np.allclose(np.exp(theta[0][free]), [40.0, 5.0, 5.0])
    assert np.allclose(np.exp(theta[1][free]), model_start(p)[free])
    # The perturbations are those of the given start the batch had before, less the last one.
    rng = np.random.default_rng(0)
    noise = 0.5 * rng.standard_normal((3, len(PARAM_NAMES)))
    expected = np.clip((theta[0] + noise[:2]) * free, p.lo, p.hi) * free
    assert np.allclose(theta[2:4], expected)


def test_no_design_start_where_kp_and_kd_are_fixed_or_one_start_is_asked():
    p = problem(free=("ki",))
    assert model_start(p) is None
    theta, _ = starts(p, 3, 0.5, 0)
    rng = np.random.default_rng(0)
    noise = 0.5 * rng.standard_normal((2, len(PARAM_NAMES)))
    theta0 = np.asarray(theta)[0]
    expected = np.clip((theta0 + noise) * p.free_mask, p.lo, p.hi) * p.free_mask
    assert np.allclose(np.asarray(theta)[1:3], expected)
    one, _ = starts(problem(), 1, 0.5, 0)
    assert np.asarray(one).shape[0] >= 1
    assert np.allclose(np.exp(np.asarray(one)[0][:3]), [40.0, 5.0, 5.0])


def test_only_the_free_gains_take_the_design():
    p = problem(free=("kp", "ki"), controller=PID(tau=0.01, v_limit=6.0))
    designed = model_start(p)
    assert designed[1] == p.start_params[1]  # kd fixed (0 unless given: not free)
    assert designed[0] != p.start_params[0]
