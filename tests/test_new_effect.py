"""Adding an effect is one module (issue 20 item 2; issue 33: one with a parameter per
direction): a throwaway effect defined here, and only here, registered with
:func:`jaxcart.effects.register`, is simulated by both simulators, fitted by
:func:`tuning.estimation.fit.fit` and named by :func:`tuning.estimation.diagnose.diagnose`,
with nothing spelled for it anywhere else: every table the library derives from the registry
is derived at call time, so an effect registered after ``tuning`` is imported is found.

The effect is a drive whose gain differs by direction: the motor sees gain_right u for a
command u > 0 and gain_left u for u < 0 [V] (a pair of parameters, one per direction: the
amplifier's two output stages, or brushes that commutate better one way). A symmetric change of
both is the motor gain (the correction gamma_scale); the effect's strength is the asymmetry
|gain_right - gain_left|. Open loop, a step of u volts is the plain cart's step of gain u volts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.effects import REGISTRY, Effect, Held, Param, register
from jaxcart.plantspec import build_plant
from jaxcart.smoothing import smooth_sign
from jaxcart.synthetic import make_recording
from tuning.estimation.diagnose import diagnose, locate, render_markdown
from tuning.estimation.fit import fit

# The library is imported before the effect is registered (above, as in a session that loads
# a plug-in effect after jaxcart and tuning): whatever the library derives from the registry
# at import time misses the new effect, whichever order the suite runs its modules in.

#: The throwaway effect's registry name (unique to this test module).
NAME = "drive_gain_by_direction_test"
#: The true gains of the recordings: full gain pushing right, 20 % less pushing left.
GAINS = {"gain_right": 1.0, "gain_left": 0.8}
#: A PD loop out 0.2 m and back to -0.1 m at 0.5 s: the drive pushes hard both ways.
PD = jc.PID(kp=80.0, kd=4.0, v_limit=6.0)
BOTH_WAYS = jc.setpoints([0.0, 0.5], [0.2, -0.1], horizon=1.0)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class GainByDirection(Effect):
    """A drive gain that differs by the command's sign.

    gain_right: the gain of commands u > 0 [1]; gain_left: of commands u < 0 [1]
    """

    gain_right: float = 1.0
    gain_left: float = 1.0

    name = NAME
    stage = "voltage"
    order = 45
    summary = "drive gain by direction: gain_right u for u > 0, gain_left u for u < 0"
    shows_in = ("command",)
    params = tuple(
        Param(
            n,
            "",
            0.0,
            5.0,
            1.0,
            "voltage",
            f"gain of the commands pushing {side}",
            role="drive",
            plausible=(0.3, 3.0),
            neutral=1.0,
            min_size=0.02,
        )
        for n, side in (("gain_right", "right"), ("gain_left", "left"))
    )

    @classmethod
    def strengths(cls, values: dict, peaks: dict):
        """The asymmetry: a change of both gains alike is gamma_scale's, not this effect's."""
        d = values["gain_right"] - values["gain_left"]
        sign = 1.0 if d >= 0 else -1.0
        weights = {"gain_right": sign, "gain_left": -sign}
        yield cls.name, abs(d), weights, f"|gain_right - gain_left| = {abs(d):.3g}", "0"

    def smooth(self, state, held: Held, smoothing, sample_time):
        mean = 0.5 * (self.gain_right + self.gain_left)
        half = 0.5 * (self.gain_right - self.gain_left)

        def f(u):
            return u * (mean + half * smooth_sign(u, smoothing.voltage))

        return Held(f(held.early), f(held.late), held.split), state

    def exact(self, state, held: Held, sample_time):
        def f(u):
            return u * (self.gain_right if u > 0.0 else self.gain_left)

        return Held(f(held.early), f(held.late), held.split), state


@pytest.fixture(scope="module")
def effect():
    """The effect registered for this module's tests, and taken out of the registry after."""
    assert NAME not in REGISTRY
    register(GainByDirection)
    try:
        yield GainByDirection
    finally:
        del REGISTRY[NAME]


@pytest.fixture(scope="module")
def recording(effect):
    """The PD loop out and back on the handout plant with the sided gain, through the IP02's
    encoder."""
    return make_recording(build_plant(GAINS), PD, BOTH_WAYS, seed=3)


def test_registered_effect_is_built_from_its_parameter_names(effect):
    plant = build_plant(GAINS)
    assert plant.structure == (NAME,)
    assert {n: float(plant.get(n)) for n in GAINS} == GAINS


@pytest.mark.parametrize("volts", [2.5, -2.5])
def test_exact_step_is_the_plain_step_of_each_directions_gain(effect, volts):
    """Open loop, u volts drive as gain u volts on the plain cart: to 1e-12 m."""
    gain = GAINS["gain_right" if volts > 0 else "gain_left"]
    exp = jc.voltage_step(volts, horizon=0.5)
    sided = jc.simulate(build_plant(GAINS), None, exp, solver=jc.Exact())
    plain = jc.simulate(jc.handout_plant(), None, jc.voltage_step(gain * volts, horizon=0.5),
                        solver=jc.Exact())  # fmt: skip
    np.testing.assert_allclose(sided.position, plain.position, rtol=0, atol=1e-12)


def test_smooth_converges_to_exact(effect):
    """The smooth simulator against the exact one as the voltage width narrows, on the loop
    out and back (measured: 1.2e-5 m at the default widths, 3.6e-11 m at 1/1000 of them; the
    effect moves the run by 45 mm)."""
    plant = build_plant(GAINS)
    exact = jc.simulate(plant, PD, BOTH_WAYS, solver=jc.Exact())
    nominal = jc.simulate(jc.handout_plant(), PD, BOTH_WAYS, solver=jc.Exact())
    assert np.max(np.abs(nominal.position - exact.position)) > 1e-3  # the effect acts
    gaps = []
    for scale in (1.0, 1e-3):
        smooth = jc.Smooth(smoothing=jc.Smoothing().scaled(scale))
        run = jc.simulate(plant, PD, BOTH_WAYS, solver=smooth)
        gaps.append(float(np.max(np.abs(np.asarray(run.position) - exact.position))))
    assert gaps[1] < 1e-8 and gaps[0] > 100 * gaps[1], gaps


def test_fitted(effect, recording):
    """fit() recovers both gains with B_eq free from the handout's start (measured: 0.99998 and
    0.79998, B_eq 5.3996 of 5.4)."""
    result = fit([recording], ("B_eq", *GAINS), progress=False)
    for n, truth in GAINS.items():
        assert result.params[n].value == pytest.approx(truth, abs=0.005), n
    assert result.params["B_eq"].value == pytest.approx(5.4, rel=0.02)
    # The encoder's floor, q / sqrt(12): nothing is left to explain.
    assert result.rms_after_exact < 1.2 * 2.275e-5 / math.sqrt(12)


@pytest.fixture(scope="module")
def diagnosis(effect, recording):
    return diagnose([recording], progress=False)


def test_diagnosed(diagnosis):
    """diagnose() names the sided gain alone as the physics left out, with both values
    (measured: 0.99985 and 0.79995, z = 3.4e4 on the asymmetry; the residual falls from
    12.3 mm to 7.3 um against the encoder's q / sqrt(12) = 6.6 um, in 10 s)."""
    d = diagnosis
    assert d.left_out == [NAME], (d.verdict, d.left_out, d.equivalent)
    params = d.to_json()["parameters"]
    for n, truth in GAINS.items():
        assert params[n]["value"] == pytest.approx(truth, abs=0.005), n
    assert d.rms_after < 1.3 * d.floor and d.rms_before > 100 * d.floor


def test_diagnosis_report_names_it_where_the_builtin_effects_are(diagnosis):
    """The Markdown gives the effect's significance beside its values, and the command test
    lists it among what a residual correlated with the command can explain."""
    row = next(line for line in render_markdown(diagnosis).splitlines() if "| gain_left |" in line)
    assert "z = " in row, row
    assert NAME in locate.points_to()["command"]
