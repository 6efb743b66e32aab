"""The tuner's iteration: one compiled function per step over the batch of starts (loss,
forward-mode gradient, adam step, projection into the box, step metrics), and the loop that
drives it through the continuation of smoothing widths to the early stop.

One compiled function does the whole iteration, so a cold run compiles one program: each
distinct program costs seconds of first-call compilation, so the iteration is never a chain of
small eager operations or a second checking program.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxcart import aot
from jaxcart.experiments import step
from jaxcart.metrics import StepInfo
from jaxcart.parallel import put, replicated
from jaxcart.plantspec import build_plant
from jaxcart.smoothing import continuation
from tuning.design.candidates import Candidates
from tuning.design.losses import (
    PARAM_NAMES,
    batched_value_and_jacfwd,
    gains_from_theta,
    make_loss,
    params_of,
)
from tuning.design.problem import TuningProblem, stack_plants
from tuning.design.settings import TuneSettings

#: Continuation: the smoothing widths are multiplied by these factors, stage by stage.
SCALES = continuation(0.125, 4)  # 1, 0.5, 0.25, 0.125
#: The step size ends at this fraction of the learning rate (cosine decay).
ALPHA = 0.1


@dataclass
class Descent:
    """Where :func:`descend` ended: the last iterate (logs), the optimizer state, the
    candidates, the history (one dict per iteration), the iterations done, and the update's
    arguments that stay on the devices (the free parameters' indices, the box's logs)."""

    theta: object
    opt_state: object
    candidates: Candidates
    history: list
    iterations: int
    free_idx: object
    box: tuple


#: Compiled iteration functions, by static configuration: a second tune() with other starts,
#: bounds or free parameters (as many, same batch size) compiles nothing.
_CACHE: dict = {}


def optimizer(learning_rate, iterations) -> optax.GradientTransformation:
    """The tuner's optimizer: optax's adam, its step decayed by optax's cosine schedule from
    ``learning_rate`` [log parameter: 0.25 is a 25 % step] to :data:`ALPHA` times it over
    ``iterations``. Both may be traced (arguments of the compiled update, so that another
    learning rate or iteration count compiles nothing): the schedule runs on the fraction of
    the iterations done, which optax's count gives."""
    decay = optax.cosine_decay_schedule(1.0, 1, alpha=ALPHA)
    return optax.adam(lambda count: learning_rate * decay(count / iterations))


def compiled_update(template, spec, settings, robust, substeps, treedef):
    """(update, init) for a static configuration, jitted once.

    update(theta, opt_state, learning_rate, iterations, free, fixed, mask, plants, scale, lo,
        hi) -> (params, theta, opt_state, per-start losses, LossInfo, StepInfo): the
        parameters at ``theta``, one step of :func:`optimizer` on the batch of starts projected
        into [lo, hi] (logs), the loss, its smooth metrics and the exact-threshold step metrics
        of the same smooth runs (robust: the worst over the plants), all from one forward-mode
        pass. init(theta, rows): the optimizer's state (:func:`initial_state`).
    """
    key = (template, spec, settings, robust, substeps, treedef)
    if key not in _CACHE:
        experiment = step(spec.step, horizon=spec.horizon, sample_time=template.sample_time)
        loss = make_loss(template, experiment, spec, settings, robust=robust, substeps=substeps)
        value_and_grad = batched_value_and_jacfwd(loss)

        def update(theta, opt_state, learning_rate, iterations, *rest):
            free, fixed, mask, plants, scale, lo, hi = rest
            values, aux, grad = value_and_grad(theta, free, fixed, mask, plants, scale)
            info = aux[1] if robust else aux
            metrics = info.metrics
            if robust:  # field-wise worst over the plants (axis 1)
                metrics = StepInfo(
                    *(
                        jnp.any(x, axis=1) if name == "diverged" else jnp.max(x, axis=1)
                        for name, x in zip(StepInfo._fields, metrics, strict=True)
                    )
                )
            grad = jnp.where(jnp.isfinite(grad), grad, 0.0)  # a blown-up run teaches nothing
            steps, opt_state = optimizer(learning_rate, iterations).update(grad, opt_state)
            params = gains_from_theta(theta, fixed[None], mask[None])
            theta = jnp.clip(optax.apply_updates(theta, steps), lo, hi) * mask[None]
            return params, theta, opt_state, values, info, metrics

        _CACHE[key] = aot.jit(update, "tune-update", key)
    return _CACHE[key]


def initial_state(theta, rows):
    """The optimizer's state for the batch of starts ``theta`` (optax's init), placed where
    the update puts it: ``rows`` for the per-start moments, a copy on every device for the
    step counts (elsewhere the second step would compile the update again)."""
    init = optimizer(1.0, 1.0).init  # (the state does not depend on the schedule)
    shardings = jax.tree.map(
        lambda x: rows if x.ndim == 2 else replicated(), jax.eval_shape(init, theta)
    )
    return jax.jit(init, out_shardings=shardings)(theta)


def descend(update, p: TuningProblem, theta, opt_state, search: TuneSettings, report, t0):
    """The adam iterations over the batch of starts, with the continuation of the smoothing
    widths (:data:`SCALES`) and the early stop; returns the :class:`Descent`."""
    ts = p.template.sample_time
    free_idx = put(np.flatnonzero(p.free_mask), np.int32)
    fixed = put(np.where(np.isfinite(p.start_params), p.start_params, 1e30), float)
    mask = put(p.free_mask)
    lo_j, hi_j = put(np.asarray(p.lo)[None], float), put(np.asarray(p.hi)[None], float)
    candidates = Candidates(p.spec, t0)
    history: list[dict] = []
    stage = Stage(np.asarray(theta))
    rate = (float(search.learning_rate), float(search.max_iterations))
    it = 0
    for it in range(search.max_iterations):  # noqa: B007 (it is used after the loop)
        scale = put(SCALES[stage.index], theta.dtype)
        params, theta, opt_state, values_now, info, metrics = update(
            theta, opt_state, *rate, free_idx, fixed, mask, p.plants_arg, scale, lo_j, hi_j
        )
        if it % search.check_every == 0:
            candidates.record(params, metrics, it, SCALES[stage.index], ts)
        entry = _history_entry(it, t0, scale, values_now, info, candidates.key)
        history.append(entry)
        report(entry)
        stage.advance(it, theta, search.stage_iterations)
        if stage.finished(it, search.patience, candidates.improved_at):
            break
    report(None)
    return Descent(theta, opt_state, candidates, history, it + 1, free_idx, (lo_j, hi_j))


def _history_entry(it, t0, scale, values_now, info, best_key) -> dict:
    """One iteration's history: its loss, the settling time and overshoot surrogates of the
    best start, the best settling time that meets the specification so far."""
    values_np = np.asarray(values_now)
    j = int(np.argmin(values_np))
    return {
        "iteration": it,
        "seconds": time.perf_counter() - t0,
        "scale": float(scale),
        "loss": float(values_np[j]),
        "settling_time": float(np.max(np.asarray(info.settling_time)[j])),
        "overshoot": float(np.max(np.asarray(info.overshoot)[j])),
        "best_settling_time": float(best_key[0]),
    }


class Stage:
    """The continuation: the stage (index into :data:`SCALES`) of the smoothing widths, the
    iteration it began and the parameters 5 iterations ago."""

    def __init__(self, anchor):
        self.index, self.start, self.anchor = 0, 0, anchor

    def advance(self, it: int, theta, stage_iterations: int) -> None:
        """Shrink the widths once the parameters stop moving at this width."""
        done_in_stage = it + 1 - self.start
        if done_in_stage % 5 == 0:
            moved = float(np.max(np.abs(np.asarray(theta) - self.anchor)))  # over 5 iterations
            last = self.index + 1 >= len(SCALES)
            if not last and (moved < 0.02 or done_in_stage >= stage_iterations):
                self.index, self.start = self.index + 1, it + 1
            self.anchor = np.asarray(theta)

    def finished(self, it: int, patience: int, improved_at: int | None) -> bool:
        """Early stop: finest width and no better point for ``patience`` iterations."""
        if self.index == len(SCALES) - 1 and it - self.start >= patience:
            last = improved_at if improved_at is not None else self.start
            return it - max(last, self.start) >= patience
        return False


def smooth_metrics(update, p: TuningProblem, descent: Descent, gains) -> StepInfo:
    """StepInfo of ``gains`` on the nominal plant, smooth loop at the finest width of the
    continuation, through the compiled update (every row the fixed ``gains``, same shapes:
    nothing new to compile; for robust tuning every plant of the stack is the nominal one)."""
    fixed = put(params_of(gains), float)
    mask = put(np.zeros(len(PARAM_NAMES), dtype=bool))  # every row: the fixed parameters
    plant, plants_arg = p.plant, p.plants_arg
    if p.robust:
        # The nominal plant with the set's effects (friction included even where f_c = 0).
        values = {n: float(plant.get(n)) for n in ("M", "B_eq") if n in plant.param_names()}
        values["f_c"] = float(plant.get("f_c")) if "f_c" in plant.param_names() else 0.0
        nominal = build_plant(values, base=plant, check=False, where="robust set")
        n_plants = jax.tree.leaves(plants_arg)[0].shape[0]
        one = jax.tree.map(lambda x: x[0], plants_arg)
        if jax.tree.structure(nominal) != jax.tree.structure(one):
            nominal = plant
        plants_arg = stack_plants([nominal] * n_plants)
    else:
        plants_arg = jax.tree.map(put, plant)
    theta = descent.theta
    scale = put(SCALES[-1], theta.dtype)
    args = (descent.free_idx, fixed, mask, plants_arg, scale, *descent.box)
    info = update(theta, descent.opt_state, 0.0, 1.0, *args)[4]
    metrics = info.metrics
    if p.robust:
        metrics = StepInfo(*(np.asarray(x)[:, 0] for x in metrics))
    return StepInfo(*(np.asarray(x)[0].item() for x in metrics))
