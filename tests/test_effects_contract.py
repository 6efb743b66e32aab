"""One contract over every registered effect (the way optax tests every optimizer): the smooth
form converges to the exact one, gradients match central differences for each parameter, no
recompilation when values change, vmap over each parameter. A new effect joins by registering:
without a case of its own in CASES it gets :func:`default_case`, derived from its declarations.
Independent references for each exact form are in tests/test_effects_reference.py."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.effects import REGISTRY
from jaxcart.exact import simulate_exact
from jaxcart.plantspec import build_plant

HORIZON = 0.6  # [s]: every case acts within it (short keeps the suite fast)
PID_STEP = jc.PID(kp=40.0, kd=3.0, ki=5.0, v_limit=6.0)

#: A closed-loop PD step on the handout plant [V/m, V s/m, V]: the default case's run.
PD_STEP = jc.PID(kp=40.0, kd=3.0, v_limit=6.0)
#: References that move the cart both ways: 0.2 m out, then back to -0.1 m at 0.3 s [m].
BOTH_WAYS = jc.setpoints([0.0, 0.3], [0.2, -0.1], horizon=HORIZON)

#: For effects whose default case does not show them plainly: plant values where the effect
#: acts plainly, the controller (None: open loop) and the experiment.
CASES = {
    "saturation": ({"v_sat": 4.0}, PID_STEP, jc.step(0.3, horizon=HORIZON)),
    "coulomb": ({"f_c": 0.6}, jc.PID(kp=20.0), jc.step(0.1, horizon=HORIZON)),
    "stiction": (
        {"f_c": 0.3, "f_s": 0.9},
        None,
        jc.voltage_sequence(np.linspace(0.0, 1.2, int(HORIZON * 1000) + 1)),
    ),
    "delay": ({"delay": 0.0037}, PID_STEP, jc.step(0.3, horizon=HORIZON)),
    "deadzone": ({"deadzone": 0.5}, jc.PID(kp=20.0), jc.step(0.1, horizon=HORIZON)),
    "spring": ({"k_s": 30.0, "y_rest": -0.1}, PID_STEP, jc.step(0.3, horizon=HORIZON)),
    "current_limit": ({"i_max": 1.2}, PID_STEP, jc.step(0.3, horizon=HORIZON)),
    # Open loop: in a closed loop a count flipped by rounding changes the whole run after it.
    "quantization": ({"quantization": 1e-4}, None, jc.voltage_step(2.0, horizon=HORIZON)),
    # The PID step overshoots: the drive reverses and the pinion crosses the play.
    "backlash": ({"backlash": 2e-4}, PID_STEP, jc.step(0.3, horizon=HORIZON)),
    "track_friction": (
        {"f_track": [0.2, 0.8, 0.3, 0.5, 0.1]},
        jc.PID(kp=25.0),
        jc.step(0.3, horizon=HORIZON),
    ),
    # Coulomb's own case, the level 0.8 N sliding right (0.4 N left).
    "coulomb_asymmetry": (
        {"f_c": 0.6, "f_c_asym": 0.2},
        jc.PID(kp=20.0),
        jc.step(0.1, horizon=HORIZON),
    ),
    # Both directions: out to 0.2 m, back to -0.1 m.
    "viscous_asymmetry": ({"B_asym": 2.0}, PID_STEP, BOTH_WAYS),
    "deadzone_asymmetry": ({"deadzone": 0.5, "deadzone_asym": 0.2}, jc.PID(kp=20.0), BOTH_WAYS),
    "voltage_offset": ({"v_offset": 0.3}, PID_STEP, jc.step(0.3, horizon=HORIZON)),
    "tilt": ({"f_tilt": 0.5}, PID_STEP, jc.step(0.3, horizon=HORIZON)),
    # Both directions, the curve growing unlike viscous friction, each way its own. Without
    # f_c: beside Coulomb friction this run's stops hold the smooth simulator at 4e-6 m at
    # every width, Coulomb's own floor on it (the curve adds nothing at rest).
    "friction_curve": (
        {"f_curve_right": [0.25, 0.3, 0.3], "f_curve_left": [0.1, 0.2, 0.4]},
        PID_STEP,
        BOTH_WAYS,
    ),
    # Stiction's ramp: after the breakaway at 0.9 N the friction falls to 0.3 N over ~1 cm/s.
    "stribeck": (
        {"f_c": 0.3, "f_s": 0.9, "v_stribeck": 0.01},
        None,
        jc.voltage_sequence(np.linspace(0.0, 1.2, int(HORIZON * 1000) + 1)),
    ),
}
NAMES = sorted(REGISTRY)
SCALES = (1.0, 0.1, 0.01, 0.001)


def default_case(name):
    """The case an effect gets from its declarations alone: its parameters and those of the
    effects it requires at their declared start values (a vector parameter: start in every
    entry), and a closed-loop PD step of 0.3 m on the handout plant."""
    cls = REGISTRY[name]
    values = {}
    for owner in (*(REGISTRY[r] for r in cls.requires), cls):
        for p in owner.params:
            values[p.name] = [p.start] * p.size if p.size else p.start
    return values, PD_STEP, jc.step(0.3, horizon=HORIZON)


def case(name):
    """The effect's explicit case, else its default case."""
    return CASES[name] if name in CASES else default_case(name)


def _run(plant, pid, exp, scale=1.0, substeps=8):
    return jc.simulate(plant, pid, exp, smoothing=jc.Smoothing().scaled(scale), substeps=substeps)


@pytest.fixture(scope="module")
def exact_runs():
    return {n: simulate_exact(build_plant(case(n)[0]), *case(n)[1:]) for n in NAMES}


def _uses_width(name):
    return any(p.width is not None for p in REGISTRY[name].params)


def test_explicit_cases_name_registered_effects():
    assert set(CASES) <= set(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_default_case_holds_the_effect_at_its_start_values(name):
    """The default case an effect without its own would get: a valid plant holding it (and
    what it requires), each parameter at its declared start value."""
    values, controller, experiment = default_case(name)
    plant = build_plant(values)
    assert name in plant.structure and set(REGISTRY[name].requires) <= set(plant.structure)
    for p in REGISTRY[name].params:
        start = [p.start] * p.size if p.size else p.start
        np.testing.assert_array_equal(np.asarray(plant.get(p.name)), np.asarray(start))
    assert controller is PD_STEP and controller.ki == 0.0 and experiment.kind == "closed_loop"


@pytest.mark.parametrize("name", NAMES)
def test_declared_parameters(name):
    cls = REGISTRY[name]
    assert cls.params and cls.stage in ("voltage", "force", "sensor") and cls.summary
    for p in cls.params:
        assert p.low <= p.start <= p.high and p.unit is not None and p.doc
    plant = build_plant(case(name)[0])
    assert plant.structure == (name,) or name in plant.structure


@pytest.mark.parametrize("name", NAMES)
def test_smooth_converges_to_exact(name, exact_runs):
    """Max position error falls >= 10x over a 1000x narrower width (effects that smooth); an
    effect with no smoothing of its own agrees to a micrometre once the controller's clip is
    narrow."""
    values, pid, exp = case(name)
    plant = build_plant(values)
    ref = exact_runs[name].position
    # A staircase's error at a count edge is q/2 at any width; what converges for a sensor
    # effect is the share of samples near an edge, i.e. the mean error.
    norm = np.mean if REGISTRY[name].stage == "sensor" else np.max
    errors = [
        float(norm(np.abs(np.asarray(_run(plant, pid, exp, s).position) - ref))) for s in SCALES
    ]
    # The effect must act: the run differs from the nominal plant's by far more than the error.
    nominal = simulate_exact(jc.handout_plant(), pid, exp).position
    assert np.max(np.abs(nominal - ref)) > 20 * errors[-1]
    if _uses_width(name):
        assert errors[0] / max(errors[-1], 1e-12) >= 10, errors
    else:
        assert errors[-1] < 1e-6, errors


def _scalar_params(name):
    out = []
    for p in REGISTRY[name].params:
        out.append(p.name)
    return out


@pytest.mark.parametrize("name", NAMES)
def test_gradients_match_central_differences(name):
    values, pid, exp = case(name)
    plant = build_plant(values)
    smoothing = jc.Smoothing()
    w = jnp.linspace(0.0, 1.0, exp.n_samples)

    for pname in _scalar_params(name):
        x0 = jnp.asarray(plant.get(pname), dtype=float)

        def loss(x, pname=pname):
            res = jc.simulate(plant.replace(**{pname: x}), pid, exp, smoothing=smoothing)
            return jnp.sum(w * res.position) / exp.n_samples

        g = jax.grad(loss)(x0)
        scale = float(jnp.max(jnp.abs(x0)))
        h = 1e-6 * (scale if scale > 0 else 1.0)
        if x0.ndim:  # a vector parameter: check one direction
            direction = jnp.linspace(1.0, -1.0, x0.shape[0])
            fd = (loss(x0 + h * direction) - loss(x0 - h * direction)) / (2 * h)
            ad = jnp.dot(g, direction)
        else:
            fd = (loss(x0 + h) - loss(x0 - h)) / (2 * h)
            ad = g
        assert np.isfinite(float(ad))
        assert float(ad) == pytest.approx(float(fd), rel=2e-3, abs=1e-9), (pname, ad, fd)


@pytest.mark.parametrize("name", NAMES)
def test_no_recompile_and_vmap(name):
    values, pid, exp = case(name)
    plant = build_plant(values)
    traces = []

    @jax.jit
    def final(p):
        traces.append(1)
        return jc.simulate(p, pid, exp).position[-1]

    pname = REGISTRY[name].params[0].name
    x0 = np.asarray(plant.get(pname), dtype=float)
    a = final(plant.replace(**{pname: x0}))
    b = final(plant.replace(**{pname: x0 * 0.9}))
    assert len(traces) == 1 and np.isfinite(a) and np.isfinite(b)
    # vmap over the parameter equals one run each.
    xs = jnp.stack([x0 * 0.8, x0, x0 * 1.1])
    batched = jax.vmap(lambda x: jc.simulate(plant.replace(**{pname: x}), pid, exp).position[-1])(
        xs
    )
    single = [final(plant.replace(**{pname: x})) for x in xs]
    np.testing.assert_allclose(np.asarray(batched), np.asarray(single), rtol=1e-10, atol=1e-12)


def test_any_combination_runs_in_both_simulators():
    values = {
        "v_sat": 5.0,
        "f_c": 0.3,
        "f_s": 0.5,
        "delay": 0.002,
        "deadzone": 0.2,
        "k_s": 5.0,
        "i_max": 1.5,
        "quantization": 2.275e-5,
        "f_c_asym": 0.1,
        "B_asym": 0.5,
        "deadzone_asym": 0.05,
        "v_offset": 0.1,
        "f_tilt": 0.2,
        "v_stribeck": 0.01,
    }
    plant = build_plant(values)
    exp = jc.step(0.3, horizon=HORIZON)
    ex = simulate_exact(plant, PID_STEP, exp)
    sm = _run(plant, PID_STEP, exp, 0.01)
    assert not ex.diverged
    assert float(np.max(np.abs(np.asarray(sm.position) - ex.position))) < 5e-4


def test_effect_order_in_the_plant_does_not_matter():
    a = jc.Plant(effects=(jc.Saturation(v_sat=4.0), jc.Delay(delay=0.002)))
    b = jc.Plant(effects=(jc.Delay(delay=0.002), jc.Saturation(v_sat=4.0)))
    exp = jc.step(0.3, horizon=HORIZON)
    np.testing.assert_array_equal(
        simulate_exact(a, PID_STEP, exp).position, simulate_exact(b, PID_STEP, exp).position
    )
    assert a.structure == b.structure == ("delay", "saturation")


def test_plant_pytree_carries_effect_values_as_leaves():
    plant = build_plant({"f_c": 0.3, "delay": 0.002})
    leaves = jax.tree_util.tree_leaves(plant)
    assert 0.3 in leaves and 0.002 in leaves
    assert dataclasses.replace(plant).structure == ("delay", "coulomb")


@pytest.mark.parametrize("name", [n for n in NAMES if hasattr(REGISTRY[n], "exact_force")])
def test_bound_exact_force_is_exact_force(name):
    """exact_force_for(drive) (the exact RK4's inner loop) is exact_force, bit for bit, over
    positions, velocities and voltages that reach every branch (a limit, a sign change)."""
    from jaxcart.exact import _as_floats, _Drive

    plant = jc.handout_plant(**case(name)[0])
    effect = _as_floats(plant.effect(name))
    drive = _Drive(float(plant.gamma), float(plant.Rm), float(plant.B_emf))
    bound = effect.exact_force_for(drive)
    for y in (-0.3, 0.0, 0.17):
        for yd in (-2.0, -1e-3, 0.0, 0.4, 3.0):
            for v in (-9.0, -0.5, 0.0, 2.5, 12.0):
                assert bound(y, yd, v) == effect.exact_force(y, yd, v, drive), (y, yd, v)
