"""Plant parameters against the handout's numbers."""

import jax
import pytest

import jaxcart as jc


def sig(x, digits=4):
    return float(f"{float(x):.{digits}g}")


def test_derived_values_match_handout():
    p = jc.Plant()
    # The handout's values to 4 significant digits.
    assert sig(p.m) == 1.073
    assert sig(p.m, 5) == 1.0731
    assert sig(p.B_emf, 5) == 7.7236
    assert sig(p.gamma, 5) == 1.7235
    assert float(p.c) == pytest.approx(5.4 + 7.7236, abs=1e-4)


def test_tap_plant_has_no_back_emf():
    p = jc.tap_plant()
    assert float(p.B_emf) == 0.0
    assert float(p.c) == 5.4
    assert sig(p.m, 5) == 1.0731  # the rotor still turns with the cart


def test_the_nominal_plant_is_the_handouts_with_no_effects():
    # Equation (0.1): no amplifier limit, no friction; the 6 V is the controller's v_limit.
    assert jc.handout_plant().effects == () and jc.Plant().effects == ()
    assert jc.voltage_limit(jc.handout_plant(), jc.PID(v_limit=6.0)) == 6.0
    assert jc.voltage_limit(jc.handout_plant(v_sat=5.0), jc.PID(v_limit=6.0)) == 5.0
    assert jc.voltage_limit(jc.handout_plant(), jc.PID()) == float("inf")


def test_named_parameters_reach_effects():
    p = jc.handout_plant(f_c=0.3, v_sat=6.0)
    assert p.get("f_c") == 0.3 and p.get("v_sat") == 6.0 and p.get("B_eq") == 5.4
    q = p.replace(f_c=0.5, B_eq=4.0, v_sat=5.0)
    assert (q.get("f_c"), q.get("B_eq"), q.get("v_sat")) == (0.5, 4.0, 5.0)
    assert p.get("f_c") == 0.3  # immutable
    with pytest.raises(KeyError, match="unknown plant parameter"):
        p.replace(B_eqq=1.0)


def test_plant_is_a_pytree_with_static_motor_flag():
    p = jc.tap_plant()
    leaves, tree = jax.tree_util.tree_flatten(p)
    assert all(isinstance(x, float) for x in leaves)
    assert jax.tree_util.tree_unflatten(tree, leaves).motor_connected is False


@pytest.mark.parametrize("field", ["M", "B_eq", "Rm"])
def test_negative_values_are_refused(field):
    with pytest.raises(ValueError, match=f"{field} = -1"):
        jc.Plant(**{field: -1.0})
