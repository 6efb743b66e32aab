"""Part (iii): f_c from the 0.1 V/s ramp, bounds on f_c from the P-control recordings, and the
steady-state error of P control k = 10 V/m against the dead band f_c / (k γ).

:func:`ramp` (which improves the model's f_c), :func:`p_bounds` and :func:`steady_state` each
return a frozen result; :func:`tuning.lab.part_iii_render.render` writes the section from the
three.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import jaxcart as jc
from jaxcart.errors import UserError
from tuning.estimation.classic import pcontrol_fc_bounds, ramp_breakaway_fc
from tuning.estimation.engine.noise import encoder_count
from tuning.estimation.fit import FitSettings
from tuning.lab import deadband, fits
from tuning.lab.context import value
from tuning.lab.data import ENCODER_PARAM
from tuning.lab.model import (
    FINAL_WINDOW,
    HORIZON,
    CartModel,
    controller_of,
    exact,
    experiment_of,
    final_error,
    source_name,
)

#: Relative slack before f_c is called outside the P-control bounds (the f_c used is itself
#: fitted, with its own error).
BOUND_SLACK = 0.02


# ---------------------------------------------------------------- f_c from the ramp


@dataclass(frozen=True, eq=False)
class RampResult:
    """f_c from the open-loop ramp. recording: the ramp (None: simulated with the model's f_c,
    ``sim``); classic: the handout's breakaway method; fit: f_c fitted with B_eq held;
    model: the cart after this step (its f_c from the fit, else the breakaway)."""

    recording: object
    model: CartModel
    classic: dict | None = None
    fit: object = None
    sim: object = None

    @property
    def source(self) -> str:
        return source_name(self.recording)

    @property
    def f_fit(self):
        return None if self.fit is None else fits.estimate(self.fit, "f_c")


def ramp(rec, start: CartModel, *, fit=fits.fit, say=lambda text: None) -> RampResult:
    """f_c from the ramp ``rec`` (B_eq of ``start`` held), or the ramp simulated on ``start``."""
    if rec is None:
        sim = exact(start.plant(), None, jc.voltage_ramp(0.1, horizon=HORIZON["ramp"]))
        return RampResult(None, start, sim=sim)
    source = source_name(rec)
    say(f"Part (iii): f_c from {source} by the handout's method (breakaway)")
    classic = handout_f_c(rec)
    say(f"Part (iii): fit of f_c to {source} (B_eq held at {start.B_eq:.3f} kg/s)")
    result = fit([rec], ("f_c",), initial={"B_eq": start.B_eq}, settings=FitSettings.warm())
    f_fit = fits.estimate(result, "f_c")
    if f_fit is not None:
        model = dataclasses.replace(
            start, f_c=f_fit.value, f_c_source=f"Part (iii), fit to the ramp {source}"
        )
    else:
        model = dataclasses.replace(
            start, f_c=classic["f_c"], f_c_source=f"Part (iii), handout's method on {source}"
        )
    return RampResult(rec, model, classic, result)


def handout_f_c(rec) -> dict:
    """f_c by the handout's ramp-breakaway method
    (:func:`tuning.estimation.classic.ramp_breakaway_fc`)."""
    est = ramp_breakaway_fc(rec)
    d = est.details
    return {
        "f_c": est.value,
        "voltage": d["voltage"],
        "time": d["time"],
        "method": est.method,
        "note": f"γ × command at the first sustained motion (3 counts for 50 ms), "
        f"t = {d['time']:.3f} s, v = {d['voltage']:.4f} V; the motion is seen a "
        f"few counts late, so this is a little high",
    }


# ---------------------------------------------------------------- bounds from P control


@dataclass(frozen=True)
class PBound:
    """Bounds on f_c [N] from one P-control recording (:func:`p_bounds`); ``error`` says why
    there are none."""

    slot: str
    name: str
    estimate: object = None
    lower: float | None = None
    q: float = 0.0
    error: str | None = None

    def to_json(self) -> dict:
        est = self.estimate
        return {**est.to_json(), "lower": self.lower, "lower_without_count": est.lower, "q": self.q}

    def outside(self, f_c: float) -> bool:
        """``f_c`` more than :data:`BOUND_SLACK` outside these bounds."""
        if self.error is not None:
            return False
        upper = self.estimate.upper
        return (self.lower is not None and f_c < (1 - BOUND_SLACK) * self.lower) or (
            upper is not None and f_c > (1 + BOUND_SLACK) * upper
        )


def p_bounds(recordings: dict) -> tuple:
    """Bounds on f_c from the P-control recordings (:func:`tuning.estimation.classic.
    pcontrol_fc_bounds`): stuck at the end, γ k (|e(inf)| − q) <= f_c (one encoder count q
    off, see :mod:`tuning.lab.deadband`); wherever it started or reversed, f_c < γ |u|.
    ``recordings``: slot -> recording (or None)."""
    out = []
    for slot in ("p_error", "p_step"):
        rec = recordings.get(slot)
        if rec is None:
            continue
        name = Path(rec.path).name
        try:
            est = pcontrol_fc_bounds(rec)
        except UserError as exc:
            out.append(PBound(slot, name, error=str(exc)))
            continue
        d, pid = est.details, rec.controller
        q = encoder_count(rec.position)
        lower = deadband.f_c_lower(d["e_inf"], float(pid.kp), d["gamma"], q, float(pid.v_limit))
        out.append(PBound(slot, name, est, lower, q))
    return tuple(out)


# ---------------------------------------------------------------- the steady-state error


@dataclass(frozen=True, eq=False)
class SteadyState:
    """P control k = 10 V/m on ``model``: the dead band b = f_c / (k γ) [m], the creep still
    left at ``t_creep`` [s], the encoder count q [m], e(inf) simulated (and measured) [m]."""

    recording: object
    model: CartModel
    controller: object
    experiment: object
    sim: object
    sim_linear: object
    gamma: float
    bound: float
    creep: float
    t_creep: float
    poles: np.ndarray
    q: float
    overdamped: bool

    @property
    def k(self) -> float:
        return float(self.controller.kp)

    @property
    def r_final(self) -> float:
        return float(np.asarray(self.experiment.signal)[-1])

    @property
    def e_sim(self) -> float:
        return final_error(self.sim.time, self.sim.error)

    @property
    def e_recorded(self):
        """The recorded error r − y [m] (None without a recording)."""
        rec = self.recording
        return None if rec is None else np.asarray(rec.reference) - rec.position

    @property
    def e_measured(self) -> float | None:
        return None if self.recording is None else final_error(self.recording.time, self.e_recorded)

    def checks(self) -> list:
        """[{what, value, bound, holds}]: e(inf) against b + creep (+ q when recorded)."""
        checks = []
        if self.recording is not None:
            checks.append(("measured", self.e_measured, self.bound + self.creep + self.q))
        checks.append(("simulated", self.e_sim, self.bound + self.creep))
        return [
            {"what": w, "value": v, "bound": lim, "holds": abs(v) <= lim * (1 + 1e-9)}
            for w, v, lim in checks
        ]


def steady_state(rec, model: CartModel, *, say=lambda text: None) -> SteadyState:
    """The steady-state error of P control with the recording ``rec`` (None: simulated)."""
    controller = controller_of(rec, jc.PID(kp=10.0))
    k = float(controller.kp)
    exp = experiment_of(rec, "p_error")
    say("Part (iii): steady-state error, measured and simulated")
    plant = model.for_recording(rec)
    gamma = float(plant.gamma)  # the simulated loop's own gain (a plant file may scale it)
    sim = exact(plant, controller, exp)
    sim_lin = exact(model.for_recording(rec, coulomb=False), controller, exp)
    step = float(np.asarray(exp.signal)[-1]) - float(exp.y0)
    m, c = float(plant.m), float(plant.c)
    # e(inf) is the mean over the last FINAL_WINDOW: the creep at its start bounds it.
    t_creep = max(0.0, float(np.asarray(sim.time)[-1]) - FINAL_WINDOW)
    return SteadyState(
        rec,
        model,
        controller,
        exp,
        sim,
        sim_lin,
        gamma,
        deadband.band(model.f_c, k, gamma),
        deadband.creep(m, c, gamma, k, model.f_c, step, t_creep),
        t_creep,
        deadband.poles(m, c, gamma, k),
        encoder_count(rec.position) if rec is not None else 0.0,
        deadband.overdamped(m, c, gamma, k),
    )


# ---------------------------------------------------------------- the part


@dataclass(frozen=True, eq=False)
class Part3:
    """Part (iii)'s three results; ``model``: the cart after it (f_c from the ramp)."""

    ramp: RampResult
    bounds: tuple
    steady: SteadyState

    @property
    def model(self) -> CartModel:
        return self.ramp.model


def compute(recordings: dict, start: CartModel, *, fit=fits.fit, say=lambda t: None) -> Part3:
    """Part (iii) from ``recordings`` (slot -> recording or None) and the model of Part (i)."""
    r = ramp(recordings.get("ramp"), start, fit=fit, say=say)
    bounds = p_bounds(recordings)
    return Part3(r, bounds, steady_state(recordings.get("p_error"), r.model, say=say))


def values(p: Part3) -> list:
    r, s, model = p.ramp, p.steady, p.model
    out = []
    if r.recording is not None:
        f_fit = r.f_fit
        out += [
            value(
                "f_c_ramp_handout",
                r.classic["f_c"],
                "N",
                "f_c, handout's method (ramp breakaway)",
                "iii",
                true_key="f_c",
            ),
            value(
                "f_c_ramp_fit",
                None if f_fit is None else f_fit.value,
                "N",
                "f_c, fit to the ramp",
                "iii",
                true_key="f_c",
            ),
        ]
    for b in p.bounds:
        if b.error is None:
            label = f"f_c lower bound from the P-control steady state ({b.name})"
            out.append(value(f"f_c_lower_{b.slot}", b.lower, "N", label, "iii", bound="lower"))
    label = f"f_c used from here on ({model.f_c_source})"
    out.append(value("f_c", model.f_c, "N", label, "iii", true_key="f_c"))
    out.append(value("e_bound", s.bound, "m", "dead band b = f_c / (k γ), k = 10 V/m", "iii"))
    out.append(value("e_inf_sim", s.e_sim, "m", "simulated e(inf), Coulomb + saturation", "iii"))
    if s.recording is not None:
        out.append(value("e_inf_measured", s.e_measured, "m", "measured e(inf)", "iii"))
    return out


def to_json(p: Part3) -> dict:
    r, s, model = p.ramp, p.steady, p.model
    ramp_out = {"recording": r.source}
    if r.recording is not None:
        ramp_out.update({"handout_method": r.classic, "fit": r.fit.to_json()})
    bounds = {b.slot: b.to_json() for b in p.bounds if b.error is None}
    if p.bounds:
        bounds["outside_bounds"] = [b.name for b in p.bounds if b.outside(model.f_c)]
    out = {"ramp": ramp_out, "p_control_bounds": bounds}
    if s.recording is not None:
        out["e_inf_measured"] = s.e_measured
    return {
        **out,
        "bound_checks": s.checks(),
        "creep": s.creep,
        ENCODER_PARAM: s.q,  # [m/count]; the key is the encoder parameter's name, as in lab.toml
        "recording": source_name(s.recording),
        "k": s.k,
        "f_c": model.f_c,
        "f_c_source": model.f_c_source,
        "bound": s.bound,
        "e_inf_simulated": s.e_sim,
    }
