"""Gradient PID tuning through the smoothed simulator, every result re-checked on the exact one.

    start parameters --> [multi-start batch, log space] --> adam steps on the smooth loss
                            ^                                  |  (tuning/design/losses.py: summed
                            in
                            |                                  v   the loop, forward mode)
                            '--- project into bounds <--- exact-threshold metrics of the same
                                                          smooth runs -> best so far; widths
                                                          shrink as the parameters settle
    end: best candidates -> exact simulator (jaxcart.exact) -> gains, or the best effort and the
    constraint that fails; every free parameter on a bound of the box is named

One compiled function does a whole iteration (loss, forward-mode gradient with one tangent per
free parameter, adam step, projection, metrics), so a cold run compiles one program. The free
parameters are any of the PID's numbers (:data:`tuning.design.losses.PARAM_NAMES`: kp, kd, ki, tau,
kb, v_limit). The default problem is the lab's: move 0.5 m, settling (2 % band) under 1 s,
overshoot under 5 %, 6 V saturation, handout plant, from the handout's gains kp = 40, kd = 5,
ki = 5. Among gains that meet it, the loss keeps driving the settling time down toward the
physical limit; the tuner stops when no better point appeared for ``patience`` iterations at
the finest width.

>>> res = tune()  # doctest: +SKIP
>>> res.meets, round(res.exact.settling_time, 3), res.on_bound  # doctest: +SKIP
(True, 0.708, {'kp': ('upper', 250.0)})
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence

import jax

from hw.control_law import PID
from jaxcart.params import Plant
from tuning.design.iteration import compiled_update, descend, initial_state
from tuning.design.losses import GAIN_NAMES, LossSettings, Spec
from tuning.design.problem import TuningProblem, starts, tuning_problem
from tuning.design.result import TuneResult, conclude
from tuning.design.settings import DEFAULT, TuneSettings
from tuning.design.wording import progress_printer


def tune(
    plant: Plant | None = None,
    *,
    spec: Spec | None = None,
    start=None,
    free: Sequence[str] = GAIN_NAMES,
    controller: PID | None = None,
    robust=False,
    n_starts: int = DEFAULT.n_starts,
    spread: float = DEFAULT.spread,
    max_iterations: int = DEFAULT.max_iterations,
    learning_rate: float = DEFAULT.learning_rate,
    patience: int = DEFAULT.patience,
    stage_iterations: int = DEFAULT.stage_iterations,
    check_every: int = DEFAULT.check_every,
    bounds: Mapping | None = None,
    settings: LossSettings | None = None,
    substeps: int | None = None,
    n_check: int = 16,
    seed: int = DEFAULT.seed,
    progress: bool | Callable[[dict], None] | None = None,
    processes=None,
) -> TuneResult | None:
    """Tune the canonical PID by gradient descent on the smooth simulator.

    plant: design model (default :func:`jaxcart.handout_plant`: the nominal model, B_eq = 5.4
        kg/s, no effects; the 6 V of the lab is the controller's ``v_limit``; a plant with
        force effects such as Coulomb friction is simulated with sub-steps, slower).
    spec: :class:`tuning.design.losses.Spec` (step 0.5 m, settling < 1 s, overshoot < 5 %).
    start: (kp, kd, ki) [V/m, V s/m, V/(m s)], all six of :data:`PARAM_NAMES`, a {name:
        value} dict or a PID; default the handout's (40, 5, 5) with the gains that are not
        free set to 0, and tau, kb, v_limit from ``controller``. What is not free stays at its
        start value.
    free: the parameters to tune among kp, kd, ki, tau [s], kb [1/s] (back-calculation
        anti-windup) and v_limit [V], e.g. ("kp", "kd") for a PD controller.
    controller: template for the other settings (tau, derivative_on, anti_windup, kb, v_limit,
        sample_time); default tau = 0.01 s, on error, no anti-windup, 6 V, 1 ms.
    robust: False; True for the default plant set (B_eq in [3, 7] kg/s, f_c in [0, 1] N, M
        within +/-10 %); a {name: (lo, hi)} dict (M as a fraction of nominal); or a list of
        Plants. The loss is then the soft maximum over the set (vmapped), and the result is
        checked on the set plus ``n_check`` random plants of the box (a list: on itself).
    The search (n_starts, spread, max_iterations, learning_rate, stage_iterations, patience,
    check_every, seed) defaults to :data:`tuning.design.settings.DEFAULT`, the one set of
    settings that ``jaxcart tune`` and the lab use too.
    n_starts: starts in the vmapped batch: the given one, a pole-placement design for the plant
        (:func:`tuning.design.problem.model_start`, where kp or kd is free) and log-normal
        perturbations of the given start (``spread``: standard deviation of their logs);
        sharded over the devices (jaxcart.parallel), padded with copies of the first start to
        a multiple of their number, so the result is the same on any number of devices.
    max_iterations, learning_rate (adam, cosine decay, in log parameter: 0.25 is a 25 % step),
        stage_iterations (most iterations at one smoothing width; fewer once the parameters
        stop moving), patience (iterations at the final width without a better point before
        stopping), check_every (iterations between looks at the exact-threshold metrics of the
        smooth runs, which pick the candidates).
    bounds: {name: (lo, hi)} limits (default :data:`DEFAULT_BOUNDS`).
    settings: :class:`tuning.design.losses.LossSettings` (weights, margins, widths).
    substeps: sub-steps per sample of the smooth simulator (default
        :func:`jaxcart.substeps.substeps_per_sample`: 1 without force effects, 2 with).
    progress: True for a status line on stderr, or a callable receiving each history dict.
    processes: a :class:`tuning.design.start_share.StartShare` for a jax.distributed run: this
        process iterates its share of the starts and every process sees the whole batch, so the
        result is the single-process one; it is returned on process 0 only (None on the others).
        Inside ``processes.carry()`` (as ``jaxcart tune`` calls it), an exception one process meets
        is raised on every process at its next exchange, none waiting for another.

    Gradients are forward-mode (one tangent per free parameter, the loss summed inside the
    simulation loop) and one compiled function does the whole iteration: loss, gradient, adam
    step, projection and the step metrics that track the best point.

    Never raises for a specification it cannot meet: ``meets`` is False, ``failing`` names the
    constraints and ``message`` says so; the best effort is returned. Runs in float64 whatever
    jax_enable_x64 says, and leaves it as it was.
    """
    t0 = time.perf_counter()
    search = TuneSettings(
        max(1, n_starts),
        spread,
        max_iterations,
        learning_rate,
        patience,
        stage_iterations,
        check_every,
        seed,
    )
    with jax.enable_x64(True):  # float64 for this call only, whatever the process has
        p = tuning_problem(
            plant,
            spec=spec or Spec(),
            start=start,
            free=free,
            controller=controller,
            robust=robust,
            bounds=bounds,
            settings=settings or LossSettings(),
            substeps=substeps,
            n_check=n_check,
            seed=seed,
        )
        return _search(p, search, progress, processes, t0)


def _search(p: TuningProblem, search: TuneSettings, progress, processes, t0) -> TuneResult | None:
    """:func:`tune` once its problem is checked and placed."""
    theta, rows = starts(p, search.n_starts, search.spread, search.seed)
    treedef = jax.tree.structure(p.plants_arg)
    update = compiled_update(p.template, p.spec, p.settings, p.robust, p.substeps, treedef)
    if processes is not None:  # this process's starts computed, the whole batch returned
        update = processes.wrap(update)
    # The optimizer state lives where the update puts it (else the second step recompiles).
    opt_state = initial_state(theta, rows)
    descent = descend(update, p, theta, opt_state, search, progress_printer(progress), t0)
    if processes is not None and not processes.finish():
        return None  # another process of a distributed run: process 0 verifies and reports
    return conclude(p, update, descent, search.n_starts, t0)
