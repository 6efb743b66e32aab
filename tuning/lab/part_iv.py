"""Part (iv): PI control k = 10 V/m, k_i = 15 V/(m s) with Coulomb friction: the simulated and
measured error, and the largest stable k_i with the fitted parameters.

:func:`compute` returns a :class:`PIResult`; :func:`render` writes the section.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import jaxcart as jc
from tuning.lab import figures, prelab
from tuning.lab.context import mm, value
from tuning.lab.model import (
    CartModel,
    controller_of,
    exact,
    experiment_of,
    final_error,
    render_source,
    source_name,
)
from tuning.lab.part_iii_render import error_traces


@dataclass(frozen=True, eq=False)
class PIResult:
    """Part (iv)'s answers on ``model``: the PI runs with and without Coulomb friction, and
    the k_i bound (:class:`tuning.lab.prelab.KiBound`) of the fitted cart at the PI's k."""

    recording: object
    model: CartModel
    controller: object
    experiment: object
    sim: object
    sim_linear: object
    bound: prelab.KiBound

    @property
    def source(self) -> str:
        return source_name(self.recording)

    @property
    def e_recorded(self):
        rec = self.recording
        return None if rec is None else np.asarray(rec.reference) - rec.position

    @property
    def rms(self) -> float | None:
        """RMS difference [m] between the simulated and the recorded position."""
        if self.recording is None:
            return None
        diff = np.asarray(self.sim.position) - self.recording.position
        return float(np.sqrt(np.mean(diff**2)))

    @property
    def stable(self) -> bool:
        return self.controller.ki < self.bound.ki_routh


def compute(rec, model: CartModel, *, say=lambda text: None) -> PIResult:
    """Part (iv) with the recording ``rec`` (None: simulations only) on ``model``."""
    controller = controller_of(rec, jc.PID(kp=10.0, ki=15.0))
    exp = experiment_of(rec, "pi")
    say("Part (iv): PI simulations")
    sim = exact(model.for_recording(rec), controller, exp)
    sim_lin = exact(model.for_recording(rec, coulomb=False), controller, exp)
    plant = model.plant()
    bound = prelab.ki_bound(
        float(plant.m), float(plant.c), float(plant.gamma), float(controller.kp)
    )
    return PIResult(rec, model, controller, exp, sim, sim_lin, bound)


def values(r: PIResult) -> list:
    out = []
    if r.recording is not None:
        out.append(value("pi_rms", r.rms, "m", "PI: RMS difference simulation − experiment", "iv"))
    return out + r.bound.values("ki_max_fitted", "iv")


def to_json(r: PIResult) -> dict:
    out = {"recording": r.source, "controller": r.controller.to_dict()}
    if r.recording is not None:
        out["final_error_measured"] = final_error(r.recording.time, r.e_recorded)
        out["rms_difference"] = r.rms
    out["final_error_simulated"] = final_error(r.sim.time, r.sim.error)
    out["pi_bound"] = r.bound.to_json()
    return out


def render(lab, r: PIResult) -> None:
    """Part (iv)'s section: the error figure and the k_i bound with the fitted parameters."""
    doc, rec, controller = lab.doc, r.recording, r.controller
    doc.heading("Part (iv): PI control, k = 10 V/m, k_i = 15 V/(m s)")
    render_source(doc, rec, "pi")
    rel = _figure(lab, r)
    doc.paragraph(
        "The integral term removes the steady-state error that Coulomb friction leaves under "
        "P control, but only slowly, and with stick-slip: the cart sticks, the integral "
        "winds up until γ v beats f_c, the cart slips, and may stick again on the other side "
        "(hunting)."
    )
    if rec is not None:
        doc.paragraph(
            f"RMS difference between the simulated and measured position: "
            f"{mm(r.rms)}; measured error at the end "
            f"{mm(final_error(rec.time, r.e_recorded))}, simulated "
            f"{mm(final_error(r.sim.time, r.sim.error))}."
        )
    what = "experiment and simulations" if rec is not None else "simulations"
    doc.figure(rel, f"Part (iv): error of PI control, {what}.")
    doc.heading("Largest stable k_i with the fitted parameters", 3)
    prelab.render_ki_bound(
        lab,
        r.bound,
        name="part4_root_locus",
        title=f"Part (iv): root locus, k = {controller.kp:g} V/m, B_eq = {r.model.B_eq:.3f} kg/s",
    )
    shown = "simulated and measured error" if rec is not None else "simulated error"
    doc.paragraph(
        f"The PI gain k_i = {controller.ki:g} V/(m s) is "
        f"{'inside' if r.stable else 'outside'} the stable range of the linear model (small "
        f"signals: the Routh bound does not account for saturation, integrator windup or "
        f"Coulomb friction, whose effect shows in the {shown} above)."
    )


def _figure(lab, r: PIResult) -> str:
    traces = []
    if r.recording is not None:
        label = f"experiment ({r.source})"
        traces.append(figures.Trace(r.recording.time, r.e_recorded * 1e3, label, True))
    traces.extend(error_traces(r.sim, r.sim_linear, r.model.f_c))
    path, rel = lab.figure_path("part4_pi_error")
    r_final = float(np.asarray(r.experiment.signal)[-1])
    c = r.controller
    figures.time_plot(
        path,
        traces,
        ylabel="error e = r − y [mm]",
        title=f"Part (iv): PI control k = {c.kp:g} V/m, k_i = "
        f"{c.ki:g} V/(m s), step {r_final:g} m: error",
        hlines=[(0.0, None, {"linewidth": 0.6})],
        zoom=(0.75 * float(np.asarray(r.sim.time)[-1]), "the last quarter, zoomed [mm]"),
    )
    return rel
