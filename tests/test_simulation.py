"""One entry point for the simulators (jaxcart/simulation.py): solvers as values, one set of
run checks with one error type (jaxcart/runcheck.py), the smooth loop's named state and pure
step, and the one sub-step policy (jaxcart/substeps.py)."""

from __future__ import annotations

import io

import jax
import numpy as np
import pytest

import jaxcart as jc
from jaxcart.smooth_sim import LoopState, loop, step
from jaxcart.substeps import (
    BACKLASH_SUBSTEPS,
    FORCE_SUBSTEPS,
    RK4_SUBSTEPS,
    SCREENING_SUBSTEPS,
)

PLANT = jc.handout_plant(v_sat=6.0)
PID = jc.PID(kp=40.0, kd=4.0)
EXP = jc.step(0.3, horizon=0.5)


def test_the_three_solvers_run_the_same_loop():
    """Linear plant, hard clip: the smooth loop is exact between samples, so it agrees with
    the exact simulator to float64 rounding (1e-12 m over 501 samples); the chunked solver runs
    the smooth loop (default widths) in chunks, the same steps as one scan."""
    exact = jc.simulate(PLANT, PID, EXP, solver=jc.Exact())
    smooth = jc.simulate(PLANT, PID, EXP, solver=jc.Smooth(smoothing=jc.EXACT_FORMS))
    assert np.max(np.abs(np.asarray(smooth.position) - exact.position)) < 1e-12
    assert np.max(np.abs(np.asarray(smooth.command) - exact.command)) < 1e-9
    chunked = jc.simulate(PLANT, PID, EXP, solver=jc.Chunked(chunk=128, out=io.StringIO()))
    whole = jc.simulate(PLANT, PID, EXP, solver=jc.Smooth())
    for field in ("position", "velocity", "command", "voltage"):
        a, b = np.asarray(getattr(chunked, field)), np.asarray(getattr(whole, field))
        assert np.max(np.abs(a - b)) < 1e-12, field
    # the keywords are shorthand for the smooth solver
    short = jc.simulate(PLANT, PID, EXP, smoothing=jc.EXACT_FORMS)
    np.testing.assert_array_equal(short.position, smooth.position)


@pytest.mark.parametrize(
    "solver", [jc.Smooth(), jc.Exact(), jc.Chunked(out=io.StringIO())], ids=type
)
def test_one_error_for_a_sample_time_mismatch(solver):
    slow = jc.PID(kp=40.0, sample_time=0.002)
    with pytest.raises(jc.IncompatibleRun, match="sample_time 0.002 s differs"):
        jc.simulate(PLANT, slow, EXP, solver=solver)
    with pytest.raises(jc.IncompatibleRun, match="needs a controller"):
        jc.simulate(PLANT, None, EXP, solver=solver)
    too_long = jc.build_plant(effects=[jc.Delay(delay=0.05, max_delay=0.01)])
    with pytest.raises(jc.IncompatibleRun, match="max_delay"):
        jc.simulate(too_long, None, jc.voltage_step(1.0, horizon=0.1), solver=solver)


def test_smooth_options_with_another_solver_are_refused():
    with pytest.raises(jc.IncompatibleRun, match="belong to the solver"):
        jc.simulate(PLANT, PID, EXP, solver=jc.Exact(), smoothing=jc.EXACT_FORMS)
    with pytest.raises(jc.IncompatibleRun, match="give jaxcart.Smooth"):
        jc.simulate(PLANT, PID, EXP, solver="exact")


def test_the_step_is_pure_and_its_state_named():
    init, bound = loop(jc.handout_plant(f_c=0.3, delay=0.002), PID, EXP)
    assert isinstance(init, LoopState)
    assert init._fields == ("position", "velocity", "controller", "effects", "transmission")
    r = EXP.signal[0]
    once, sample = bound(init, r)
    again, _ = bound(init, r)  # the same state in, the same state out: nothing kept inside
    for a, b in zip(jax.tree.leaves(once), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(a, b)
    assert bound.func is step
    jitted, _ = jax.jit(bound)(init, r)
    np.testing.assert_allclose(jitted.position, once.position, rtol=0, atol=1e-15)
    assert float(sample.position) == float(init.position)  # the read before the step


def test_one_substep_policy():
    assert jc.substeps_per_sample(jc.handout_plant()) == 1
    assert jc.substeps_per_sample(jc.handout_plant(f_c=0.3)) == FORCE_SUBSTEPS == 2
    assert jc.substeps_per_sample(jc.handout_plant(backlash=1e-4)) == BACKLASH_SUBSTEPS == 4
    assert jc.substeps_per_sample(jc.handout_plant(f_c=0.3), screening=True) == 1
    assert SCREENING_SUBSTEPS == 1
    assert jc.substeps_per_sample(jc.handout_plant(), rk4=True) == RK4_SUBSTEPS == 5
