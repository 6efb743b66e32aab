"""Part (iii) of the report drawn from its results (:mod:`tuning.lab.part_iii`): the ramp, the
P-control bounds on f_c and the steady-state error against the dead band. Drawing reads the
results; the computing module never imports this one.
"""

from __future__ import annotations

import numpy as np

import jaxcart as jc
from tuning.lab import deadband, figures, fits
from tuning.lab.context import fmt, mm
from tuning.lab.model import FINAL_WINDOW, render_source, source_name
from tuning.lab.part_iii import BOUND_SLACK, Part3


def render(lab, p: Part3) -> None:
    """Part (iii)'s section."""
    lab.doc.heading("Part (iii): Coulomb friction and the steady-state error")
    ramp(lab, p.ramp, p.model)
    bounds(lab, p.bounds, p.model)
    steady_state(lab, p.steady)


def ramp(lab, r, model) -> None:
    """The ramp's subsection: both methods (or the simulation) and the figure."""
    doc = lab.doc
    gamma = float(jc.Plant().gamma)
    doc.heading("f_c from the voltage ramp (0.1 V/s)", 3)
    render_source(doc, r.recording, "ramp")
    marks = []
    if r.recording is not None:
        rec, classic = r.recording, r.classic
        u = np.asarray(rec.command if rec.command is not None else rec.experiment.signal)
        top = [
            figures.Trace(rec.time, rec.position * 1e3, f"experiment ({r.source})", True),
            figures.Trace(
                r.fit.segments[0].time,
                np.asarray(r.fit.segments[0].after_exact) * 1e3,
                f"model, fitted f_c = {fmt(model.f_c, 4)} N",
            ),
        ]
        bottom = [figures.Trace(rec.time, u, "experiment: voltage command v", True)]
        marks.append(
            (
                classic["voltage"],
                f"breakaway seen at {classic['voltage']:.4f} V (handout's method)",
                {"linestyle": ":"},
            )
        )
        _ramp_methods(doc, r, model)
    else:
        doc.paragraph(
            f"The ramp below is simulated with f_c = {fmt(model.f_c)} N from {model.f_c_source}."
        )
        sim = r.sim
        label = f"simulation, f_c = {fmt(model.f_c, 4)} N (position; below, its voltage v)"
        top = [figures.Trace(sim.time, np.asarray(sim.position) * 1e3, label)]
        # One legend for both panels: the voltage is the same simulation's, not a second line.
        bottom = [figures.Trace(sim.time, np.asarray(sim.command), "_voltage command v")]
    marks.append(
        (
            model.f_c / gamma,
            f"f_c / γ = {model.f_c / gamma:.4f} V",
            {"linestyle": "--", "color": "tab:red"},
        )
    )
    path, rel = lab.figure_path("part3_ramp")
    figures.two_panel(
        path,
        top,
        bottom,
        top_ylabel="position y [mm]",
        bottom_ylabel="voltage v [V]",
        title=f"Part (iii): open-loop voltage ramp 0.1 V/s ({r.source})",
        bottom_hlines=marks,
    )
    doc.figure(
        rel,
        "Part (iii): the voltage ramp; the cart breaks away once γ v exceeds f_c "
        "(the voltage f_c/γ dashed).",
    )


def _ramp_methods(doc, r, model) -> None:
    doc.paragraph(
        "The cart stays put until the drive γ v exceeds the friction f_c: the handout "
        "reads f_c = γ v at the voltage where the cart starts to move. The fit instead "
        "simulates the whole ramp (stick, breakaway, acceleration) with B_eq from Part (i) "
        "and fits f_c to the positions."
    )
    doc.table(
        ["method", "f_c [N]", "notes"],
        [
            ["handout's method (breakaway)", f"{r.classic['f_c']:.4f}", r.classic["note"]],
            [
                f"fit (B_eq = {model.B_eq:.3f} kg/s held)",
                fits.pm(r.f_fit, "").strip(),
                f"RMS position error {mm(r.fit.rms_after_exact)} (exact simulator)",
            ],
        ],
        numeric=[False, True, False],
    )


def bounds(lab, found, model) -> None:
    """The P-control bounds on f_c: a table and a note where the f_c used falls outside."""
    if not found:
        return
    rows = []
    for b in found:
        if b.error is not None:
            rows.append([b.name, "n/a", "n/a", b.error])
            continue
        d = b.estimate.details
        rows.append(
            [
                b.name,
                fmt(b.lower),
                fmt(b.estimate.upper),
                f"e(inf) = {mm(d['e_inf'])}, u(inf) = {d['u_inf']:.4f} V, q = {mm(b.q, 4)}",
            ]
        )
    lab.doc.paragraph(
        "A check on f_c from the P-control recordings: a cart at rest at the end with "
        "recorded error e(inf) has γ k (|e(inf)| − q) ≤ f_c (a lower bound; the encoder "
        "reads up to one count q below the cart), and wherever it started from rest or "
        "reversed the drive beat friction, f_c < γ |u| there (an upper bound)."
    )
    lab.doc.table(
        ["recording", "lower bound [N]", "upper bound [N]", "notes"],
        rows,
        numeric=[False, True, True, False],
    )
    outside = [b.name for b in found if b.outside(model.f_c)]
    if outside:
        lab.doc.note(
            f"The f_c used ({model.f_c:.3f} N, {model.f_c_source}) is more than "
            f"{BOUND_SLACK:.0%} outside the bounds of {', '.join(outside)}: the friction "
            f"in that experiment differs from the model's."
        )


def steady_state(lab, s) -> None:
    """The steady-state error subsection: the dead band, the checks, the figure."""
    doc, model = lab.doc, s.model
    doc.heading("Steady-state error of P control, k = 10 V/m", 3)
    render_source(doc, s.recording, "p_error")
    rel = _error_figure(lab, s)
    doc.paragraph(
        f"With Coulomb friction the cart can rest only where the P controller's force k γ |e| "
        f"does not beat f_c: the dead band |e(inf)| ≤ b = f_c / (k γ) = {fmt(model.f_c)} / "
        f"({s.k:g} × {s.gamma:.4f}) = {mm(s.bound, 4)}. {_approach(s)} The encoder reads "
        f"whole counts below the cart, so a recorded error can exceed the true one by up to "
        f"one count q. The bound that a run of finite length must meet is therefore b + creep "
        f"(+ q when recorded)."
    )
    doc.table(["quantity", "value"], _rows(s), numeric=[False, True])
    verdicts = s.checks()
    for v in verdicts:
        if not v["holds"]:
            q = s.q if v["what"] == "measured" else 0.0
            implied = deadband.f_c_lower(v["value"], s.k, s.gamma, q)
            doc.note(
                f"The {v['what']} error {mm(v['value'], 4)} is outside the stated bound "
                f"{mm(v['bound'], 4)}: it implies f_c ≥ {implied:.4f} N, more than the "
                f"{model.f_c:.4f} N used ({model.f_c_source}); that f_c is low for this "
                f"experiment, or the cart is still moving at the end."
            )
    if all(v["holds"] for v in verdicts):
        doc.paragraph(
            "Both errors lie within their stated bounds."
            if len(verdicts) > 1
            else "The simulated error lies within its stated bound."
        )
    what = "experiment and simulations" if s.recording is not None else "simulations"
    doc.figure(
        rel,
        f"Part (iii): error of P control, {what}, with the dead band ±f_c/(k γ) "
        f"dotted (the error starts at {s.r_final * 1e3:g} mm).",
    )


def _approach(s) -> str:
    pole_text = " and ".join(f"{p.real:.3g}" for p in sorted(s.poles, key=lambda p: -p.real))
    if not s.overdamped:
        return (
            "Here the loop m s² + c s + k γ has complex poles: the cart overshoots and sticks "
            "at a reversal inside the band."
        )
    return (
        f"Here the loop m s² + c s + k γ has real poles ({pole_text} 1/s): coming from one "
        f"side without overshoot, the cart creeps towards the edge of the band, its "
        f"distance from the edge falling as e^({sorted(s.poles.real)[-1]:.3g} t), and never "
        f"stops inside it in finite time; at the start of the last {FINAL_WINDOW:g} s of "
        f"the run (over which e(inf) is averaged, from {s.t_creep:g} s) it is "
        f"still {mm(s.creep, 2)} beyond the edge (linear model)."
    )


def _rows(s) -> list:
    rows = [["dead band b = f_c / (k γ)", mm(s.bound, 4)]]
    if s.creep > 0:
        rows.append(
            [f"still to creep at {s.t_creep:g} s (linear model, slower pole)", mm(s.creep, 2)]
        )
    if s.recording is not None:
        rows += [
            ["encoder count q (a recorded error reads up to q high)", mm(s.q, 4)],
            [
                f"measured e(inf) (mean of the last {FINAL_WINDOW:g} s of "
                f"{s.recording.time[-1]:.1f} s)",
                mm(s.e_measured, 4),
            ],
            ["its stated bound b + creep + q", mm(s.bound + s.creep + s.q, 4)],
        ]
    return rows + [
        ["simulated e(inf) (Coulomb friction + saturation, exact stick-slip)", mm(s.e_sim, 4)],
        ["its stated bound b + creep", mm(s.bound + s.creep, 4)],
    ]


def _error_figure(lab, s) -> str:
    traces = []
    if s.recording is not None:
        label = f"experiment ({source_name(s.recording)})"
        traces.append(figures.Trace(s.recording.time, s.e_recorded * 1e3, label, True))
    traces.extend(error_traces(s.sim, s.sim_linear, s.model.f_c))
    bound = s.bound
    path, rel = lab.figure_path("part3_error")
    top = max(3.0 * bound, 0.25 * abs(s.r_final)) * 1e3
    figures.time_plot(
        path,
        traces,
        ylabel="error e = r − y [mm]",
        title=f"Part (iii): P control k = {s.k:g} V/m, step {s.r_final:g} m: error (zoomed)",
        hlines=[
            (bound * 1e3, f"dead band ±f_c/(k γ) = ±{bound * 1e3:.2f} mm", {"linestyle": ":"}),
            (-bound * 1e3, None, {"linestyle": ":"}),
        ],
        ylim=(-1.5 * bound * 1e3, top),
    )
    return rel


def error_traces(sim, sim_lin, f_c):
    """Simulated error [mm] with Coulomb friction and saturation, and without friction."""
    return [
        figures.Trace(
            sim.time,
            np.asarray(sim.error) * 1e3,
            f"simulation with Coulomb friction f_c = {f_c:.3f} N and saturation",
        ),
        figures.Trace(
            sim_lin.time, np.asarray(sim_lin.error) * 1e3, "simulation without Coulomb friction"
        ),
    ]
