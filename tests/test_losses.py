"""The tuning loss summed inside the loop (tuning/design/losses.py, jaxcart/accumulators.py).

References: the same loss computed from a stored response by the surrogates of
jaxcart.surrogates (plant_loss), the exact step metrics of jaxcart.metrics.step_metrics on the
same smooth run, and central finite differences for the forward-mode gradient.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.metrics import step_metrics
from tuning.design.losses import (
    PARAM_NAMES,
    LossSettings,
    Spec,
    batched_value_and_jacfwd,
    controller_with,
    make_loss,
    plant_loss,
    stream_loss,
)

SPEC, SETTINGS = Spec(), LossSettings()
EXPERIMENT = jc.step(0.5, horizon=SPEC.horizon)
PLANT = jc.handout_plant()
#: Back-calculation anti-windup, so that every one of the six parameters acts.
TEMPLATE = jc.PID(v_limit=6.0, anti_windup="back_calculation")


@pytest.fixture(scope="module")
def losses():
    def both(params, scale):
        a = plant_loss(params, PLANT, TEMPLATE, EXPERIMENT, SPEC, SETTINGS, scale)
        b = stream_loss(params, PLANT, TEMPLATE, EXPERIMENT, SPEC, SETTINGS, scale)
        pid = controller_with(TEMPLATE, params)
        c = step_metrics(PLANT, pid, EXPERIMENT, smoothing=SETTINGS.smoothing.scaled(scale))
        return a, b, c

    return jax.jit(both)


# A feasible PID (hinges off) and the handout's start (hinges on: slow, overshooting).
POINTS = [(100.0, 6.0, 2.0, 0.01, 1.0, 6.0), (40.0, 5.0, 5.0, 0.02, 5.0, 5.0)]


@pytest.mark.parametrize("params, scale", [(POINTS[0], 1.0), (POINTS[1], 0.125)])
def test_loss_summed_in_the_loop_equals_the_loss_of_the_stored_trace(losses, params, scale):
    (ref, ref_info), (loss, info), expected = losses(jnp.asarray(params), scale)
    # Same surrogates, another order of summation: 1e-9 relative.
    assert float(loss) == pytest.approx(float(ref), rel=1e-9)
    assert float(info.settling_time) == pytest.approx(float(ref_info.settling_time), rel=1e-9)
    assert float(info.overshoot) == pytest.approx(float(ref_info.overshoot), rel=1e-9, abs=1e-9)
    # Its exact-threshold metrics are step_metrics' of the same smooth run: the loop packs its
    # carry (jaxcart.accumulators), which may round the trajectory differently by an ulp.
    for name, got, want in zip(expected._fields, info.metrics, expected, strict=True):
        assert float(got) == pytest.approx(float(want), rel=1e-12, abs=1e-15), name


@pytest.mark.parametrize(
    "effects",
    [(jc.Quantization(), jc.Delay(delay=0.002)), (jc.Coulomb(f_c=0.5),)],
    ids=["sensor-and-delay", "coulomb"],
)
def test_loss_summed_in_the_loop_with_effects(effects):
    """The loop packs its state into one vector only without force effects (and then with the
    sensor's and the delay line's states): both carries hold the stored-trace loss, 1e-9."""
    plant = dataclasses.replace(PLANT, effects=effects)
    params = jnp.asarray(POINTS[0])

    def both(params):
        a = plant_loss(params, plant, TEMPLATE, EXPERIMENT, SPEC, SETTINGS, 1.0)
        b = stream_loss(params, plant, TEMPLATE, EXPERIMENT, SPEC, SETTINGS, 1.0)
        pid = controller_with(TEMPLATE, params)
        return a, b, step_metrics(plant, pid, EXPERIMENT, smoothing=SETTINGS.smoothing)

    (ref, ref_info), (loss, info), expected = jax.jit(both)(params)
    assert float(loss) == pytest.approx(float(ref), rel=1e-9)
    assert float(info.settling_time) == pytest.approx(float(ref_info.settling_time), rel=1e-9)
    assert float(info.overshoot) == pytest.approx(float(ref_info.overshoot), rel=1e-9, abs=1e-9)
    for name, got, want in zip(expected._fields, info.metrics, expected, strict=True):
        assert float(got) == pytest.approx(float(want), rel=1e-12, abs=1e-15), name


def test_forward_mode_gradient_matches_central_differences():
    """Forward mode over every free parameter, against central differences of the loss in log
    parameters (h = 1e-5): relative tolerance 1e-4."""
    loss = make_loss(TEMPLATE, EXPERIMENT, SPEC, SETTINGS, robust=False)
    grad_fn = jax.jit(batched_value_and_jacfwd(loss))
    value = jax.jit(lambda th, fixed, mask: loss(th, fixed, mask, PLANT, 0.5)[0])
    mask = jnp.ones(len(PARAM_NAMES), dtype=bool)
    fixed = jnp.asarray(POINTS[0])
    theta = jnp.log(jnp.asarray(POINTS))
    free = jnp.arange(len(PARAM_NAMES), dtype=jnp.int32)
    values, _, grad = grad_fn(theta, free, fixed, mask, PLANT, 0.5)
    grad = np.asarray(grad)
    h = 1e-5
    for i in range(theta.shape[0]):
        assert float(values[i]) == pytest.approx(float(value(theta[i], fixed, mask)), rel=1e-12)
        scale = np.abs(grad[i]).max()
        assert scale > 0 and np.all(np.isfinite(grad[i]))
        for j, name in enumerate(PARAM_NAMES):
            e = jnp.zeros(len(PARAM_NAMES)).at[j].set(h)
            fd = float(value(theta[i] + e, fixed, mask)) - float(value(theta[i] - e, fixed, mask))
            fd /= 2 * h
            assert grad[i, j] == pytest.approx(fd, rel=1e-4, abs=1e-6 * scale), (i, name)


def test_rows_of_forward_mode_equal_per_run_jacobians():
    """jaxcart.accumulators.value_and_jacfwd_rows (tangents laid out across the runs) against
    jax.jacfwd of each run alone, with a per-row argument, shared arguments and aux: values
    and aux to 1e-14, gradients to 1e-12 (the same operations, batched otherwise: vectorized
    sin rounds otherwise than the scalar one)."""
    from jaxcart.accumulators import value_and_jacfwd_rows

    def fn(u, row, c):
        value = jnp.sin(u[0] * row) + c * u[1] ** 3 + u[0] * u[1]
        return value, {"twice": 2.0 * value, "row": row}

    U = jnp.asarray([[0.3, -1.2], [1.5, 0.7], [-0.4, 2.0]])
    rows = jnp.asarray([1.0, 2.0, -3.0])
    (values, aux), grads = jax.jit(value_and_jacfwd_rows(fn, has_aux=True))(U, rows, 0.5)
    assert grads.shape == U.shape
    for i in range(U.shape[0]):
        value, aux_i = fn(U[i], rows[i], 0.5)
        grad = jax.jacfwd(lambda u, i=i: fn(u, rows[i], 0.5)[0])(U[i])
        assert float(values[i]) == pytest.approx(float(value), rel=1e-14)
        assert float(aux["twice"][i]) == pytest.approx(float(aux_i["twice"]), rel=1e-14)
        assert float(aux["row"][i]) == float(rows[i])
        np.testing.assert_allclose(np.asarray(grads[i]), np.asarray(grad), rtol=1e-12)
    plain = value_and_jacfwd_rows(lambda u, row, c: fn(u, row, c)[0])
    values2, grads2 = jax.jit(plain)(U, rows, 0.5)
    np.testing.assert_array_equal(np.asarray(values2), np.asarray(values))
    np.testing.assert_allclose(np.asarray(grads2), np.asarray(grads), rtol=1e-14)
