"""Part (ii): P control k = 50 V/m, a 0.4 m step: the experiment against simulations without
and with the ±6 V saturation, and B_eq re-estimated to fit the experiment.

:func:`compute` returns a :class:`P50Result`; :func:`agreement` compares its B_eq with the
model's (the tap's); :func:`render` writes the section.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import jaxcart as jc
from jaxcart.plots import plot_runs, reference_run
from tuning.estimation.fit import FitSettings
from tuning.lab import fits
from tuning.lab.context import V_SAT, fmt, mm, value
from tuning.lab.model import (
    CartModel,
    controller_of,
    crop,
    exact,
    no_limit,
    render_source,
    run,
    source_name,
)

HORIZON = 3.0  # [s], the handout's three seconds


@dataclass(frozen=True, eq=False)
class P50Result:
    """Part (ii)'s answers. model: the cart simulated (B_eq, f_c of the earlier parts);
    sim_free/sim_sat/sim_coulomb: exact runs without saturation, with it, and with Coulomb
    friction too (None when f_c = 0); refit/refit_coulomb: B_eq fitted to the recording with
    the handout's model and with f_c held (None without a recording or f_c); sim_refit: the
    run with the re-estimated B_eq; info_free/info_sat: their step metrics."""

    recording: object
    controller: object
    experiment: object
    model: CartModel
    sim_free: object
    sim_sat: object
    sim_coulomb: object = None
    refit: object = None
    refit_coulomb: object = None
    sim_refit: object = None
    info_free: object = None
    info_sat: object = None

    @property
    def source(self) -> str:
        return source_name(self.recording)

    @property
    def amplitude(self) -> float:
        """The step [m]."""
        return float(np.asarray(self.experiment.signal)[-1])

    @property
    def b_refit(self):
        return None if self.refit is None else fits.estimate(self.refit, "B_eq")

    @property
    def b_refit_coulomb(self):
        return None if self.refit_coulomb is None else fits.estimate(self.refit_coulomb, "B_eq")

    @property
    def best(self):
        """(estimate, fit) of B_eq with the best model this part fitted (with f_c if any)."""
        if self.refit_coulomb is not None:
            return self.b_refit_coulomb, self.refit_coulomb
        return self.b_refit, self.refit

    @property
    def final_error_measured(self) -> float | None:
        """r − y at the recording's end [m]."""
        rec = self.recording
        return None if rec is None else float(self.amplitude - rec.position[-1])


def compute(rec, model: CartModel, *, fit=fits.fit, say=lambda text: None) -> P50Result:
    """Part (ii) with the recording ``rec`` (None: simulations only) on ``model``."""
    controller = controller_of(rec, jc.PID(kp=50.0, v_limit=V_SAT))
    exp = rec.experiment_for(HORIZON) if rec is not None else jc.step(0.4, horizon=HORIZON)
    say("Part (ii): simulations without and with saturation")
    plant = model.for_recording
    sim_free = exact(plant(rec, saturation=False, coulomb=False), no_limit(controller), exp)
    sim_sat = exact(plant(rec, coulomb=False), controller, exp)
    sim_c = exact(plant(rec), controller, exp) if model.f_c > 0 else None
    refit = refit_c = sim_re = None
    if rec is not None:
        say(f"Part (ii): re-estimating B_eq to fit {source_name(rec)}")
        refit = fit([rec], ("B_eq",), initial={"B_eq": model.B_eq}, settings=FitSettings.warm())
        b_ii = fits.estimate(refit, "B_eq")
        if b_ii is not None:
            sim_re = exact(plant(rec, coulomb=False, B_eq=b_ii.value), controller, exp)
        if model.f_c > 0:
            initial = {"B_eq": model.B_eq, "f_c": model.f_c}
            refit_c = fit([rec], ("B_eq",), initial=initial, settings=FitSettings.warm())
    return P50Result(
        rec,
        controller,
        exp,
        model,
        sim_free,
        sim_sat,
        sim_c,
        refit,
        refit_c,
        sim_re,
        jc.step_info(sim_free),
        jc.step_info(sim_sat, v_limit=V_SAT),
    )


# ---------------------------------------------------------------- B_eq of the tap and the step


@dataclass(frozen=True)
class Agreement:
    """B_eq from the step [kg/s] against the tap's (the model's): agree within 2 combined
    standard errors or 10 %. rms [m]: the step fit's RMS position error (exact simulator)."""

    B_eq_tap: float
    B_eq_tap_stderr: float
    tap_source: str
    B_eq_step: float
    B_eq_step_stderr: float
    rms: float

    @property
    def apart(self) -> float:
        """How many combined standard errors apart."""
        diff = abs(self.B_eq_step - self.B_eq_tap)
        return diff / math.hypot(self.B_eq_step_stderr, self.B_eq_tap_stderr)

    @property
    def agree(self) -> bool:
        diff = abs(self.B_eq_step - self.B_eq_tap)
        return self.apart <= 2 or diff <= 0.1 * self.B_eq_tap

    def text(self, diagnosis: bool) -> str:
        """The report's sentence (a note pointing at the diagnosis when they disagree)."""
        both = (
            f"B_eq from this step ({self.B_eq_step:.3f} ± {fmt(self.B_eq_step_stderr, 2)} "
            f"kg/s) and from the tap ({self.B_eq_tap:.3f} ± {fmt(self.B_eq_tap_stderr, 2)} "
            f"kg/s, {self.tap_source})"
        )
        if self.agree:
            return f"{both} agree ({self.apart:.1f} standard errors apart): one cart, one B_eq."
        where = (
            "The [diagnosis](#diagnosis-what-the-model-leaves-out) below fits the effects the "
            "model may leave out to each recording and compares the B_eq they give."
            if diagnosis
            else "`jaxcart diagnose` on both files (or this lab without --no-diagnosis) looks "
            "for the effects the model leaves out."
        )
        big, small = max(self.B_eq_step, self.B_eq_tap), min(self.B_eq_step, self.B_eq_tap)
        return (
            f"{both} disagree: {self.apart:.1f} standard errors apart, a factor "
            f"{big / small:.2g}. One cart has one viscous friction, so the model leaves out "
            f"physics that the two experiments see differently (here the motor is connected "
            f"and driven, in the tap it is not), as the fit's RMS error of {mm(self.rms)} also "
            f"shows. The later parts keep the tap's value. {where}"
        )

    def to_json(self, diagnosis: bool) -> dict:
        return {
            "B_eq_tap": self.B_eq_tap,
            "B_eq_step": self.B_eq_step,
            "standard_errors_apart": self.apart,
            "agree": self.agree,
            "text": self.text(diagnosis),
        }


def agreement(r: P50Result) -> Agreement | None:
    """Part (ii)'s best B_eq against the model's, when both have a standard error."""
    est, result = r.best
    if est is None or r.model.B_eq_stderr is None:
        return None
    m = r.model
    return Agreement(
        m.B_eq, m.B_eq_stderr, m.B_eq_source, est.value, est.stderr, result.rms_after_exact
    )


# ---------------------------------------------------------------- numbers


def values(r: P50Result) -> list:
    if r.recording is None:
        return []
    b_ii, f_c = r.b_refit, r.model.f_c
    out = [
        value(
            "B_eq_p50",
            None if b_ii is None else b_ii.value,
            "kg/s",
            "B_eq re-estimated on Part (ii), handout model (no Coulomb)",
            "ii",
        )
    ]
    if r.refit_coulomb is not None:
        b_c = r.b_refit_coulomb
        out.append(
            value(
                "B_eq_p50_coulomb",
                None if b_c is None else b_c.value,
                "kg/s",
                f"B_eq re-estimated on Part (ii) with f_c = {f_c:.3f} N held",
                "ii",
                true_key="B_eq",
            )
        )
    return out


def to_json(r: P50Result, agreed: Agreement | None, *, diagnosis: bool) -> dict:
    out = {
        "recording": r.source,
        "controller": r.controller.to_dict(),
        "B_eq_model": r.model.B_eq,
        "f_c_model": r.model.f_c,
    }
    if r.recording is not None:
        out["refit"] = r.refit.to_json()
        if r.refit_coulomb is not None:
            out["refit_with_coulomb"] = r.refit_coulomb.to_json()
        out["final_error_measured"] = r.final_error_measured
        out["B_eq_agreement"] = None if agreed is None else agreed.to_json(diagnosis)
    out["simulations"] = {
        "without_saturation": r.info_free.as_dict(),
        "with_saturation": r.info_sat.as_dict(),
    }
    return out


# ---------------------------------------------------------------- render


def render(lab, r: P50Result, agreed: Agreement | None) -> None:
    """Part (ii)'s section: simulations, the re-estimated B_eq, its agreement, the figure."""
    doc, m, kp = lab.doc, r.model, r.controller.kp
    doc.heading("Part (ii): P control, k = 50 V/m, step of 0.4 m")
    render_source(doc, r.recording, "p_step")
    rel = _figure(lab, r)
    free, sat = r.info_free, r.info_sat
    doc.paragraph(
        f"Simulations with the model of Part (i) (B_eq = {m.B_eq:.3f} kg/s, no Coulomb "
        f"friction, as in the handout): without saturation the voltage starts at "
        f"k r = {kp * r.amplitude:g} V and the cart settles in "
        f"{free.settling_time:.3f} s (overshoot {free.overshoot:.1f} %); with the "
        f"±{V_SAT:g} V saturation the voltage is clipped for {sat.saturation_time:.3f} s "
        f"and the cart settles in {sat.settling_time:.3f} s (overshoot "
        f"{sat.overshoot:.1f} %)."
        + (
            f" The full model adds the Coulomb friction f_c = {m.f_c:.3f} N ({m.f_c_source})."
            if m.f_c > 0
            else ""
        )
    )
    if r.recording is not None:
        doc.paragraph(
            "B_eq re-estimated so that the model fits this experiment (least "
            "squares on the position, checked on the exact simulator):"
        )
        doc.table(
            ["quantity", "value", "RMS position error (exact sim.)"],
            _refit_rows(r),
            numeric=[False, True, True],
        )
    if agreed is not None:
        (doc.paragraph if agreed.agree else doc.note)(agreed.text(lab.diagnosis))
    what = "experiment and simulations" if r.recording is not None else "simulations"
    doc.figure(
        rel,
        f"Part (ii): {what} without and with saturation, position and voltage over three seconds.",
    )


def _refit_rows(r: P50Result) -> list:
    m = r.model
    rows = [
        [
            "B_eq re-estimated (handout model: saturation, no Coulomb friction)",
            fits.pm(r.b_refit, "kg/s"),
            mm(r.refit.rms_after_exact),
        ]
    ]
    if r.refit_coulomb is not None:
        rows.append(
            [
                f"B_eq re-estimated with Coulomb friction f_c = {m.f_c:.3f} N held "
                f"({m.f_c_source})",
                fits.pm(r.b_refit_coulomb, "kg/s"),
                mm(r.refit_coulomb.rms_after_exact),
            ]
        )
    rows.append(["measured final error r − y(end)", mm(r.final_error_measured), ""])
    return rows


def _figure(lab, r: P50Result) -> str:
    m, rec = r.model, r.recording
    runs = [reference_run(r.sim_sat.time, r.sim_sat.reference)]
    if rec is not None:
        t, y, v = crop(rec.time, rec.position, rec.command, horizon=HORIZON)
        runs.append(run(f"experiment ({r.source})", t, y, v, role="experiment"))
    sims = [
        (f"model without saturation (B_eq = {m.B_eq:.3f} kg/s)", r.sim_free),
        (f"model with saturation ±{V_SAT:g} V (B_eq = {m.B_eq:.3f} kg/s)", r.sim_sat),
    ]
    if r.sim_coulomb is not None:
        label = f"model with saturation and Coulomb friction f_c = {m.f_c:.3f} N"
        sims.append((label, r.sim_coulomb))
    if r.sim_refit is not None:
        label = f"model with saturation, B_eq re-estimated = {r.b_refit.value:.3f} kg/s"
        sims.append((label, r.sim_refit))
    runs += [run(label, s.time, s.position, s.command) for label, s in sims]
    path, rel = lab.figure_path("part2_p50")
    plot_runs(
        runs,
        title=f"Part (ii): P control k = {r.controller.kp:g} V/m, step {r.amplitude:g} "
        f"m: position (top) and voltage (bottom)",
        path=path,
        v_limit=V_SAT,
        zoom=True,
    )
    return rel
