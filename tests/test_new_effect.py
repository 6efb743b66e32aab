"""Adding an effect is one module (issue 20 item 2): a throwaway effect defined here, and only
here, registered with :func:`jaxcart.effects.register`, is simulated by both simulators, fitted
by :func:`tuning.estimation.fit.fit` and named by :func:`tuning.estimation.diagnose.diagnose`,
with nothing spelled for it anywhere else: every table the library derives from the registry
is derived at call time, so an effect registered after ``tuning`` is imported is found.

The effect is a tilted track: gravity's component along the track is a constant force
f_tilt = M g sin(theta) [N] on the cart (0.5 N is a 3.1 degree tilt under the 0.94 kg cart).
Under P or PD control without integral action the loop holds it with a steady error: the cart
settles where kp gamma (y - r) = f_tilt, past the reference by f_tilt / (kp gamma) [m].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.effects import REGISTRY, Effect, Param, register
from jaxcart.plantspec import build_plant
from jaxcart.synthetic import make_recording
from tuning.estimation.diagnose import diagnose, locate, render_markdown
from tuning.estimation.fit import fit

# The library is imported before the effect is registered (above, as in a session that loads
# a plug-in effect after jaxcart and tuning): whatever the library derives from the registry
# at import time misses the new effect, whichever order the suite runs its modules in.

#: The throwaway effect's registry name (unique to this test module).
NAME = "tilted_track_test"
#: The true tilt force of the recordings [N] (positive: along +y, with the step).
F_TILT = 0.5
#: The PD step where the bias shows: kp [V/m], kd [V s/m], 6 V software limit, a 0.2 m step.
PD = jc.PID(kp=80.0, kd=4.0, v_limit=6.0)
HORIZON = 1.0  # [s]: within 0.03 mm of rest by 0.8 s; short keeps the diagnosis fast
SETTLED = 2.0  # [s]: at rest to a micrometre


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class TiltedTrack(Effect):
    """A constant force along the track [N] (gravity on a tilted track).

    f_tilt: the force along +y [N]
    """

    f_tilt: float = 0.0

    name = NAME
    stage = "force"
    summary = "tilted track: a constant force f_tilt along the track"
    shows_in = ("position",)
    params = (
        Param(
            "f_tilt",
            "N",
            -20.0,
            20.0,
            0.2,
            None,
            "force along the track (gravity on a tilt)",
            role="cart",
            plausible=(-3.0, 3.0),
            neutral=0.0,
            min_size=0.02,
        ),
    )

    def smooth_force(self, y, yd, v, smoothing, plant):
        return self.f_tilt * jnp.ones_like(y)

    def exact_force(self, y, yd, v, plant):
        return float(self.f_tilt)


@pytest.fixture(scope="module")
def tilt():
    """The effect registered for this module's tests, and taken out of the registry after."""
    assert NAME not in REGISTRY
    register(TiltedTrack)
    try:
        yield TiltedTrack
    finally:
        del REGISTRY[NAME]


@pytest.fixture(scope="module")
def recording(tilt):
    """A PD step on the handout plant tilted by F_TILT, through the IP02's encoder."""
    plant = build_plant({"f_tilt": F_TILT})
    return make_recording(plant, PD, jc.step(0.2, horizon=HORIZON), seed=3)


def test_registered_effect_is_built_from_its_parameter_name(tilt):
    plant = build_plant({"f_tilt": F_TILT})
    assert plant.structure == (NAME,) and float(plant.get("f_tilt")) == F_TILT


def test_simulated_by_both_simulators(tilt):
    """The exact simulator against the closed-form steady state, and the smooth one against
    the exact as the smoothing narrows (the force has no corner of its own: only the
    controller's clip is smoothed, and at 1/1000 of its width the two runs agree)."""
    plant = build_plant({"f_tilt": F_TILT})
    exp = jc.step(0.2, horizon=SETTLED)
    exact = jc.simulate(plant, PD, exp, solver=jc.Exact())
    # Steady state of a PD loop with a constant force: kp (r - y) gamma + f = 0 (the clip is
    # off by then: kp e = 0.29 V), so y = r + f / (kp gamma), 3.6 mm past the reference.
    y_inf = 0.2 + F_TILT / (PD.kp * float(plant.gamma))
    assert float(exact.position[-1]) == pytest.approx(y_inf, abs=1e-6)
    nominal = jc.simulate(jc.handout_plant(), PD, exp, solver=jc.Exact())
    assert abs(float(nominal.position[-1]) - 0.2) < 1e-6  # the bias is the tilt's
    gaps = []
    for scale in (1.0, 1e-3):
        smooth = jc.Smooth(smoothing=jc.Smoothing().scaled(scale))
        run = jc.simulate(plant, PD, exp, solver=smooth)
        gaps.append(float(np.max(np.abs(np.asarray(run.position) - exact.position))))
    # Measured: 6.7 um at the default widths, 8e-12 m at 1/1000 of them (the tilt's own
    # offset is 3.6 mm).
    assert gaps[0] < 2e-5 and gaps[1] < 1e-9, gaps


def test_fitted(tilt, recording):
    """fit() recovers f_tilt with B_eq free from the handout's start."""
    result = fit([recording], ("B_eq", "f_tilt"), progress=False)
    assert result.params["f_tilt"].value == pytest.approx(F_TILT, abs=0.01)
    assert result.params["B_eq"].value == pytest.approx(5.4, rel=0.02)
    # The encoder's floor, q / sqrt(12): nothing is left to explain.
    assert result.rms_after_exact < 1.2 * 2.275e-5 / math.sqrt(12)


@pytest.fixture(scope="module")
def diagnosis(tilt, recording):
    return diagnose([recording], progress=False)


def test_diagnosed(diagnosis):
    """diagnose() names the tilt as the physics left out, with its value."""
    d = diagnosis
    assert d.left_out == [NAME], (d.verdict, d.left_out)
    # Measured: 0.50001 N; the residual falls from 2.36 mm to the encoder floor (7.6 um
    # against q / sqrt(12) = 6.6 um).
    assert d.to_json()["parameters"]["f_tilt"]["value"] == pytest.approx(F_TILT, abs=0.01)
    assert d.rms_after < 1.3 * d.floor and d.rms_before > 100 * d.floor


def test_diagnosis_report_names_it_where_the_builtin_effects_are(diagnosis):
    """The Markdown gives the tilt's significance beside its value, and the position test
    lists it among what a residual correlated with position can explain."""
    row = next(line for line in render_markdown(diagnosis).splitlines() if "| f_tilt |" in line)
    assert "z = " in row, row
    assert NAME in locate.points_to()["position"]
