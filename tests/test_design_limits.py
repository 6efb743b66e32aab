"""The gains' limits derived from the cart (tuning.design.limits): kp from the drive's voltage at
the settling band's edge (the software limit, the amplifier's, a current limit's Rm i_max), kd
from the encoder's ripple against the control law itself; the tuner's box takes them unless the
user bounds a gain, and a result says which one sets it."""

import dataclasses

import pytest

import jaxcart as jc
from hw.control_law import pid_init, pid_update
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.plantspec import build_plant
from tuning.design.limits import RIPPLE, binding_text, gain_limits
from tuning.design.losses import LossSettings, Spec
from tuning.design.problem import DEFAULT_BOUNDS, tuning_problem

LAB = jc.PID(tau=0.01, v_limit=6.0)


@pytest.mark.parametrize(
    ("values", "volts", "what"),
    [
        ({}, 6.0, "software limit"),
        ({"v_sat": 5.1}, 5.1, "amplifier"),
        ({"f_c": 0.4, "i_max": 1.2}, 2.6 * 1.2, "current limit"),
    ],
)
def test_kp_keeps_the_loop_linear_inside_the_settling_band(values, volts, what):
    """kp <= V / (2 % of the step): the drive's most voltage at rest at the band's edge."""
    plant = build_plant(values) if values else jc.handout_plant()
    for step in (0.5, 0.2):
        kp = gain_limits(plant, LAB, step)["kp"]
        assert kp.bound == pytest.approx(volts / (0.02 * step), rel=1e-12)
        assert what in kp.what and f"{kp.bound:.4g}" in kp.why


def _one_count(pid) -> float:
    """The control law's change of command for one count more, read in one sample [V]."""
    state = pid_init(pid, 0.5, 0.2)
    _, v0, _ = pid_update(pid, state, 0.5, 0.2)
    _, v1, _ = pid_update(pid, state, 0.5, 0.2 - ENCODER_RESOLUTION)
    return v1 - v0


@pytest.mark.parametrize("tau", [0.01, 0.002])
def test_kd_is_where_one_encoder_count_moves_the_command_by_the_ripple_allowed(tau):
    """At kp and kd on their limits, one count moves the command by exactly RIPPLE (the
    control law's own answer); the lab's filter allows about 90 V s/m, a light one much less."""
    pid = dataclasses.replace(LAB, tau=tau)
    limits = gain_limits(jc.handout_plant(), pid, 0.5)
    at = dataclasses.replace(pid, kp=limits["kp"].bound, kd=limits["kd"].bound)
    assert _one_count(at) == pytest.approx(RIPPLE, rel=1e-9)
    assert limits["kd"].what == "the encoder's ripple"
    free_tau = gain_limits(jc.handout_plant(), pid, 0.5, tau_low=1e-4)["kd"].bound
    assert free_tau < limits["kd"].bound
    if tau == 0.01:
        assert 85.0 < limits["kd"].bound < 95.0


def _problem(plant, bounds=None, free=("kp", "kd", "ki")):
    return tuning_problem(
        plant, spec=Spec(), start=None, free=free, controller=LAB, robust=False,
        bounds=bounds, settings=LossSettings(), substeps=None, n_check=0, seed=0,
    )  # fmt: skip


def test_the_tuners_box_takes_the_limits_unless_the_user_bounds_a_gain():
    p = _problem(build_plant({"f_c": 0.4, "i_max": 1.2}))
    assert p.box["kp"] == (DEFAULT_BOUNDS["kp"][0], pytest.approx(2.6 * 1.2 / 0.01))
    assert p.box["kd"][1] == pytest.approx(p.limits["kd"].bound)
    assert p.box["ki"] == DEFAULT_BOUNDS["ki"]
    mine = _problem(jc.handout_plant(), bounds={"kp": (1.0, 100.0)})
    assert mine.box["kp"] == (1.0, 100.0) and set(mine.limits) == {"kd"}
    free_tau = _problem(jc.handout_plant(), free=("kp", "kd", "ki", "tau"))
    assert free_tau.box["kd"][1] < p.box["kd"][1]  # at the box's lowest tau


def test_binding_says_which_limit_sets_a_design():
    limits = gain_limits(build_plant({"f_c": 0.4, "i_max": 1.2}), LAB, 0.5)
    on = dataclasses.replace(LAB, kp=limits["kp"].bound * 0.999, kd=5.0)
    assert binding_text(on, limits).startswith("the design is set by the current limit")
    inside = dataclasses.replace(LAB, kp=100.0, kd=5.0)
    assert binding_text(inside, limits).startswith("no limit of the cart binds")
