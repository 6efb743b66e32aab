"""Part (v): the PID design: the simulated and measured step with the metrics of both, and the
handout's slider moves simulated with the tuned gains.

:func:`compute` returns a :class:`PIDResult` from the recording, the model and the pre-lab's
tuned gains; :func:`tuning.lab.part_v_render.render` writes the section.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

import jaxcart as jc
from jaxcart.metrics import step_info
from jaxcart.smooth_sim import Response
from tuning.lab.context import V_SAT, value
from tuning.lab.model import CartModel, controller_of, exact, experiment_of, source_name

#: The design problem: overshoot [%] and settling time [s] bounds.
OVERSHOOT_SPEC, SETTLING_SPEC = 5.0, 1.0
#: Part (v)'s slider moves: (time [s], position [m]).
SLIDER = ((0.0, 0.2), (2.5, 0.0), (5.0, -0.2), (7.5, 0.2))
SLIDER_HORIZON = 10.0
METRICS = ("rise_time", "overshoot", "settling_time", "steady_state_error")


@dataclass(frozen=True, eq=False)
class PIDResult:
    """Part (v)'s answers on ``model``. tuned: the pre-lab's PID; controller: the recording's
    (the tuned one without a recording); sim/info_sim: the step simulated with it;
    info_rec: the recording's metrics; sim_tuned/info_tuned: the tuned gains on the same
    model when the recording ran others; slider/moves: the slider run and each move's
    (from [m], to [m], metrics)."""

    recording: object
    model: CartModel
    tuned: object
    controller: object
    experiment: object
    sim: object
    info_sim: object
    info_rec: object = None
    sim_tuned: object = None
    info_tuned: object = None
    slider: object = None
    moves: tuple = ()
    #: The plant the step ran on (the recorded run's own drive values where the joint fit has
    #: them), None: ``model``'s.
    plant: object = None

    @property
    def source(self) -> str:
        return source_name(self.recording)

    @property
    def same(self) -> bool:
        """The recording ran the tuned gains (or there is no recording)."""
        return self.recording is None or same_gains(self.controller, self.tuned)

    @property
    def failing(self) -> list:
        """[(move number, metrics)] of the slider moves that miss the design problem."""
        return [
            (i + 1, info)
            for i, (_, _, info) in enumerate(self.moves)
            if not info.meets(SETTLING_SPEC, OVERSHOOT_SPEC)
        ]


def compute(rec, model: CartModel, tuned=None, *, plant=None, say=lambda text: None) -> PIDResult:
    """Part (v) with the recording ``rec`` (None: simulation only) on ``model``; ``tuned``:
    the pre-lab's PID (None: the handout's kp = 40, kd = 5, ki = 5); ``plant``: the cart the
    recorded run is simulated on (its own drive values; None: ``model``'s)."""
    tuned = tuned if tuned is not None else jc.PID(kp=40.0, kd=5.0, ki=5.0, v_limit=V_SAT)
    controller = controller_of(rec, tuned)
    exp = experiment_of(rec, "pid")
    plant = model.for_recording(rec) if plant is None else plant
    say("Part (v): PID step, simulated and measured")
    sim = exact(plant, controller, exp)
    extra = {}
    if rec is not None:
        extra["info_rec"] = jc.step_info(rec.as_response(), v_limit=V_SAT)
    if rec is not None and not same_gains(controller, tuned):
        sim_t = exact(plant, tuned, exp)
        extra.update(sim_tuned=sim_t, info_tuned=jc.step_info(sim_t, v_limit=V_SAT))
    say("Part (v): slider moves with the tuned gains")
    times, targets = zip(*SLIDER, strict=True)
    slider = exact(model.plant(), tuned, jc.setpoints(times, targets, horizon=SLIDER_HORIZON))
    return PIDResult(
        rec,
        model,
        tuned,
        controller,
        exp,
        sim,
        jc.step_info(sim, v_limit=V_SAT),
        slider=slider,
        moves=tuple(slider_moves(slider, times)),
        plant=plant,
        **extra,
    )


def same_gains(a, b, rel: float = 5e-4) -> bool:
    """The same PID up to the 4 digits a file keeps (kp, kd, ki, tau)."""
    return all(
        math.isclose(float(getattr(a, n)), float(getattr(b, n)), rel_tol=rel, abs_tol=1e-9)
        for n in ("kp", "kd", "ki", "tau")
    )


def slider_moves(response, times):
    """Step metrics of each move of a piecewise-constant reference."""
    t = np.asarray(response.time)
    bounds = [int(np.searchsorted(t, x - 1e-9)) for x in times] + [t.size]
    previous = float(response.position[0])
    moves = []
    signals = ("time", "position", "velocity", "reference", "error", "command", "voltage")
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        part = {f.name: getattr(response, f.name) for f in dataclasses.fields(Response)}
        for name in (*signals, "unlimited"):
            if part.get(name) is not None:
                part[name] = np.asarray(part[name])[a:b]
        part["time"] = part["time"] - part["time"][0]
        target = float(np.asarray(response.reference)[a])
        moves.append((previous, target, step_info(Response(**part), v_limit=V_SAT)))
        previous = target
    return moves


def values(r: PIDResult) -> list:
    out = []
    units = {"overshoot": "%", "steady_state_error": "m"}
    for which, info in (("measured", r.info_rec), ("simulated", r.info_sim)):
        if info is None:
            continue
        for name in METRICS:
            out.append(
                value(
                    f"pid_{which}_{name}",
                    getattr(info, name),
                    units.get(name, "s"),
                    f"PID step, {which} {name.replace('_', ' ')}",
                    "v",
                )
            )
    return out


def to_json(r: PIDResult) -> dict:
    out = {"recording": r.source, "controller": r.controller.to_dict()}
    if r.info_rec is not None:
        out["measured"] = r.info_rec.as_dict()
    out["simulated"] = r.info_sim.as_dict()
    if r.info_tuned is not None:
        out["tuned_on_fitted_model"] = r.info_tuned.as_dict()
    out["slider"] = [{"from": a, "to": b, **info.as_dict()} for a, b, info in r.moves]
    out["slider_failing_moves"] = [i for i, _ in r.failing]
    return out
