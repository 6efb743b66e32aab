"""The margins of a design (tuning.design.margins) against independent references: the gain and
delay margins against the eigenvalues of the discrete closed loop (jaxcart.plausibility, written
apart from python-control), the peak sensitivity against python-control's stability margin on
the linear loop without a delay, the ripple against the control law itself; the hunting warning
where integral action meets stiction."""

import dataclasses
import math

import control
import numpy as np
import pytest

import jaxcart as jc
from hw.control_law import pid_init, pid_update
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.plantspec import build_plant
from jaxcart.plausibility import closed_loop_eigenvalues
from tuning.design.margins import loop_transfer, margins, ripple

#: A lab cart with the real recordings' delay (11.9 ms), and one without.
DELAYED = build_plant({"B_eq": 1.5, "delay": 0.0119})
LINEAR = jc.handout_plant()
DESIGNS = {
    "retuned": jc.PID(kp=250.0, ki=0.6, kd=9.66, v_limit=6.0),
    "pd-unfiltered": jc.PID(kp=55.0, kd=5.0, tau=0.0, v_limit=6.0),
    "handout": jc.PID(kp=40.0, kd=5.0, ki=5.0),
}
#: The frequency grid's resolution leaves the margins this close to the eigenvalues' boundary.
REL = 0.01


def _radius(pid, plant) -> float:
    """The largest |z| of the closed loop's modes (without ki the integral's state is a mode
    of its own at z = 1 that the loop never sees)."""
    z = closed_loop_eigenvalues(pid, plant)
    if pid.ki == 0:
        z = z[np.abs(z - 1.0) > 1e-9]
    return float(np.max(np.abs(z)))


def _scaled(pid, factor):
    return dataclasses.replace(pid, kp=pid.kp * factor, ki=pid.ki * factor, kd=pid.kd * factor)


@pytest.mark.parametrize("name", ["retuned", "pd-unfiltered"])
def test_gain_margin_is_where_the_closed_loop_turns_unstable(name):
    """Every gain times the gain margin puts the loop's eigenvalues on the unit circle: 1 %
    less is stable, 1 % more is not (the eigenvalues of jaxcart.plausibility's loop matrix,
    delay line included)."""
    pid = DESIGNS[name]
    m = margins(DELAYED, pid)
    assert 1.5 < m.gain_margin < 100
    assert _radius(_scaled(pid, m.gain_margin * (1 - REL)), DELAYED) < 1.0
    assert _radius(_scaled(pid, m.gain_margin * (1 + REL)), DELAYED) > 1.0


@pytest.mark.parametrize("name", ["retuned", "pd-unfiltered"])
def test_delay_margin_is_where_more_delay_turns_it_unstable(name):
    """The phase margin as a delay (phase margin / crossover): the cart's delay plus 97 % of it
    is stable, plus 103 % is not (the split-sample delay line of the loop matrix)."""
    pid = DESIGNS[name]
    m = margins(DELAYED, pid)
    assert m.delay == pytest.approx(0.0119)
    assert 20.0 < m.phase_margin < 90.0
    for factor, stable in ((0.97, True), (1.03, False)):
        delay = 0.0119 + factor * m.delay_margin
        plant = dataclasses.replace(
            DELAYED, effects=(dataclasses.replace(DELAYED.effects[0], delay=delay, max_delay=0.2),)
        )
        assert (_radius(pid, plant) < 1.0) == stable, factor


@pytest.mark.parametrize("name", list(DESIGNS))
def test_peak_sensitivity_against_python_control(name):
    """On the linear loop without a delay, Ms = 1 / python-control's stability margin (the
    least distance of the Nyquist curve from -1, on python-control's own frequency grid), to
    0.5 %; the phase margin and the gain margin (the least factor above 1: with integral action
    the loop also has one below) as its margins give them, to 0.1 %. (Its polynomial method
    finds spurious crossovers on these discrete loops, as python-control itself warns.)"""
    pid = DESIGNS[name]
    m = margins(LINEAR, pid)
    gms, pms, sms, *_ = control.stability_margins(
        loop_transfer(LINEAR, pid), method="frd", returnall=True
    )
    assert m.peak_sensitivity == pytest.approx(1.0 / np.min(sms), rel=5e-3)
    assert m.phase_margin == pytest.approx(np.min(pms), rel=1e-3)
    up = [g for g in np.atleast_1d(gms) if g > 1]
    if up:
        assert m.gain_margin == pytest.approx(min(up), rel=1e-3)
    else:
        assert math.isinf(m.gain_margin)
    assert m.delay == 0.0 and 1.0 <= m.peak_sensitivity < 2.0


@pytest.mark.parametrize("tau", [0.0, 0.01])
def test_ripple_is_one_count_through_the_control_law(tau):
    """One encoder count more, read within one sample, moves the command by q (kp + kd /
    (tau + Ts)): the control law's own answer (hw.control_law), a pure difference and the
    lab's filter; kd = 9 V s/m unfiltered makes the issue's 0.2 V."""
    pid = jc.PID(kp=250.0, kd=9.0, ki=1.0, tau=tau)
    state = pid_init(pid, 0.5, 0.1)
    _, v0, _ = pid_update(pid, state, 0.5, 0.1)
    _, v1, _ = pid_update(pid, state, 0.5, 0.1 - ENCODER_RESOLUTION)
    assert ripple(pid) == pytest.approx(v1 - v0, rel=1e-9)
    if tau == 0.0:
        assert ripple(dataclasses.replace(pid, kp=0.0)) == pytest.approx(0.2, abs=0.005)


def test_hunting_is_warned_for_integral_action_with_stiction():
    sticky = build_plant({"B_eq": 4.0, "f_c": 0.3, "f_s": 0.6})
    pid = DESIGNS["handout"]
    assert "hunts" in margins(sticky, pid).hunting
    assert margins(sticky, dataclasses.replace(pid, ki=0.0)).hunting == ""
    assert margins(build_plant({"B_eq": 4.0, "f_c": 0.3}), pid).hunting == ""
