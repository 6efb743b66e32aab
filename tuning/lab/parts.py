"""The lab's Parts (i) to (v): each computes what its "hand in" items ask, draws its figures,
writes its section of the report and records its numbers.

The model of the cart improves as the parts go: Part (i) fits B_eq (and f_c) to the tap,
Part (iii) measures f_c; later parts simulate with the best-known values (``Lab.plant``).
Every simulation here is the exact one (:func:`jaxcart.exact.simulate_exact`: hard clip,
event-exact stick-slip, the 1 ms digital loop); fits run through the smooth simulator
(:mod:`tuning.estimation.fit`) and report the exact simulator's error.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from jaxcart.errors import UserError
from jaxcart.metrics import SETTLING_BAND
from tuning.lab import deadband
from tuning.lab.context import HANDOUT_B_EQ, V_SAT, Lab, fmt, mm
from tuning.lab.inputs import SLOTS

#: Fit settings for the report: the default continuation for the tap (a real tap needs it),
#: a short Levenberg-Marquardt polish where the start is already close.
QUICK_FIT = {"widths": (1e-3, 1e-4), "adam_steps": 0, "lm_iterations": 15}
#: Horizons [s] of the simulations where no recording sets them.
HORIZON = {"p_step": 3.0, "ramp": 6.0, "p_error": 5.0, "pi": 10.0, "pid": 3.0}
STEP = {"p_step": 0.4, "p_error": 0.2, "pi": 0.2, "pid": 0.5}
#: e(inf) of a record is the mean error over its last FINAL_WINDOW [s].
FINAL_WINDOW = 0.1
#: The design problem: overshoot [%] and settling time [s] bounds.
OVERSHOOT_SPEC, SETTLING_SPEC = 5.0, 1.0
#: Part (v)'s slider moves: (time [s], position [m]).
SLIDER = ((0.0, 0.2), (2.5, 0.0), (5.0, -0.2), (7.5, 0.2))
SLIDER_HORIZON = 10.0
#: Relative slack before f_c is called outside the P-control bounds (the f_c used is itself
#: fitted, with its own error).
BOUND_SLACK = 0.02


# ---------------------------------------------------------------- shared helpers


def _fit(recordings, params, *, initial=None, quick=False):
    from tuning.estimation.fit import FitSettings, fit

    settings = FitSettings(**QUICK_FIT) if quick else FitSettings()
    return fit(recordings, params, initial=initial, settings=settings, progress=False)


def _estimate(result, name):
    est = result.params.get(name)
    return None if est is None or not est.identifiable else est


def _pm(est, unit, digits=5) -> str:
    if est is None:
        return "not identifiable"
    return f"{fmt(est.value, digits)} ± {fmt(est.stderr, 2)} {unit}"


def _exact(plant, controller, experiment):
    from jaxcart.exact import simulate_exact

    return simulate_exact(plant, controller, experiment)


def _no_limit(controller):
    return dataclasses.replace(controller, v_limit=math.inf)


def _crop(time, *arrays, horizon):
    keep = np.asarray(time) <= horizon + 1e-9
    return [np.asarray(time)[keep]] + [None if a is None else np.asarray(a)[keep] for a in arrays]


def _source(lab: Lab, slot: str) -> str:
    rec = lab.recording(slot)
    part, what = SLOTS[slot]
    if rec is None:
        lab.doc.note(
            f"No recording for Part ({part}) ({what}): this section shows simulation only."
        )
        return "simulation only"
    name = Path(rec.path).name
    desc = rec.meta.get("description")
    lab.doc.paragraph(f"Recording: `{name}`" + (f" ({desc})." if desc else "."))
    return name


def _run(label, time, position, voltage=None, role="simulation"):
    from jaxcart.plots import Run

    return Run(
        label,
        np.asarray(time),
        np.asarray(position),
        None if voltage is None else np.asarray(voltage),
        role,
    )


def _final_error(time, error, window=None) -> float:
    """e(inf) from a record [m]: the mean error over its last ``window`` seconds."""
    window = FINAL_WINDOW if window is None else window
    time, error = np.asarray(time), np.asarray(error)
    return float(np.mean(error[time >= time[-1] - window]))


def _controller(rec, default):
    return rec.controller if rec is not None and rec.controller is not None else default


def _experiment(rec, slot):
    import jaxcart as jc

    if rec is not None:
        return rec.experiment
    if slot == "ramp":
        return jc.voltage_ramp(0.1, horizon=HORIZON[slot])
    return jc.step(STEP[slot], horizon=HORIZON[slot])


def _plant_for(lab: Lab, rec, **flags):
    plant = lab.plant(**flags)
    return rec.plant(plant) if rec is not None and rec.plant_overrides else plant


# ---------------------------------------------------------------- Part (i)


def part_i(lab: Lab) -> None:
    """B_eq from the tap, by the handout's method and by a full fit; model vs experiment."""
    import jaxcart as jc
    from tuning.lab import figures

    doc = lab.doc
    doc.heading("Part (i): B_eq from the tap test")
    rec = lab.recording("tap")
    source = _source(lab, "tap")
    out = {"recording": source}
    nominal = jc.Plant()
    m, gamma, B_emf = float(nominal.m), float(nominal.gamma), float(nominal.B_emf)
    if rec is None:
        doc.paragraph(
            f"Without a tap recording B_eq stays at the handout's estimate "
            f"{HANDOUT_B_EQ} kg/s and the model has no Coulomb friction."
        )
    else:
        lab.say(f"Part (i): B_eq from {source} by the handout's method (log-linear)")
        classic = _handout_b_eq(rec)
        lab.say(
            f"Part (i): full fit of B_eq and f_c to {source} (smooth simulator, "
            f"Levenberg-Marquardt)"
        )
        result = _fit([rec], ("B_eq", "f_c"))
        seg = result.segments[0]
        b_fit = _estimate(result, "B_eq")
        f_fit = _estimate(result, "f_c")
        if b_fit is None:
            raise UserError(
                f"{rec.path}: B_eq cannot be determined from this tap recording "
                f"({result.params['B_eq'].note}); record a longer coast"
            )
        lab.B_eq, lab.B_eq_source = b_fit.value, f"Part (i), full fit to {source}"
        lab.B_eq_stderr = b_fit.stderr
        if f_fit is not None:
            lab.f_c, lab.f_c_source = f_fit.value, f"Part (i), full fit to {source}"
        lab.value(
            "B_eq_tap_handout",
            classic["B_eq"],
            "kg/s",
            "B_eq, handout's log-linear method (tap)",
            "i",
            true_key="B_eq",
        )
        lab.value(
            "B_eq_tap_fit", b_fit.value, "kg/s", "B_eq, full fit to the tap", "i", true_key="B_eq"
        )
        lab.value(
            "f_c_tap_fit",
            None if f_fit is None else f_fit.value,
            "N",
            "f_c, full fit to the tap",
            "i",
            true_key="f_c",
        )

        doc.paragraph(
            f"**Handout's method.** While the cart coasts with viscous friction only, "
            f"v(t) = v0 e^(−(B_eq/m) t): a least-squares line through ln|v| against t has the "
            f"slope −B_eq/m. Here the slope is {classic['slope']:.4f} 1/s, so B_eq = −slope × m "
            f"= {-classic['slope']:.4f} × {classic['mass']:.4f} kg = "
            f"**{classic['B_eq']:.4f} kg/s** (regression standard error "
            f"{fmt(classic['stderr'], 2)} kg/s; m = M + M_J, the motor's rotor still turns)."
        )
        rel_ll = _loglinear_figure(lab, classic, source)
        doc.figure(
            rel_ll,
            "Part (i): the handout's method: ln|v| of the coasting cart and the "
            "least-squares line (the points beyond the line's end were not "
            "used).",
        )
        doc.paragraph(
            "**Full fit.** The smooth simulator (motor unplugged: B_emf = 0, no drive) runs the "
            "coast with viscous and Coulomb friction; B_eq, f_c and the cart's position and "
            "speed at the start of the coast are fitted to the positions by "
            "Levenberg-Marquardt and the result is checked on the exact stick-slip simulator. "
            "Standard errors are autocorrelation-robust (HAC). Coulomb friction, which the "
            "log-linear method leaves out, decelerates the cart more at low speed, bends the "
            "ln|v| line down and makes the handout's B_eq come out too large."
        )
        rows = [
            [
                "handout's method (log-linear)",
                f"{classic['B_eq']:.4f}",
                "not modelled",
                classic["note"],
            ],
            [
                "full fit (exact-simulator check)",
                _pm(b_fit, "").strip(),
                _pm(f_fit, "").strip(),
                f"RMS position error {mm(result.rms_after_exact)} over {seg.time[0]:.3f} to "
                f"{seg.time[-1]:.3f} s",
            ],
        ]
        doc.table(
            ["method", "B_eq [kg/s]", "f_c [N]", "notes"], rows, numeric=[False, True, True, False]
        )

        yd0, y0 = seg.nuisance["yd0"].value, seg.nuisance["y0"].value
        t_c, y_c = classic["curve"]
        traces = [
            figures.Trace(rec.time, rec.position * 1e3, f"experiment ({source})", True),
            figures.Trace(
                seg.time,
                np.asarray(seg.after_exact) * 1e3,
                f"model, full fit: B_eq = {b_fit.value:.3f} kg/s, f_c = "
                f"{fmt(None if f_fit is None else f_fit.value, 3)} N",
            ),
            figures.Trace(
                t_c,
                np.asarray(y_c) * 1e3,
                f"model, handout's method: B_eq = {classic['B_eq']:.3f} kg/s, viscous only",
            ),
        ]
        path, rel = lab.figure_path("part1_tap")
        pad = 0.25
        figures.time_plot(
            path,
            traces,
            ylabel="position y [mm]",
            title=f"Part (i): tap test, motor unplugged ({source})",
            xlim=(max(0.0, seg.time[0] - pad), min(rec.time[-1], seg.time[-1] + pad)),
            legend="lower right",
        )
        doc.figure(
            rel,
            f"Part (i): the tap recording and both models over the coast (the full "
            f"fit starts at y0 = {y0 * 1e3:.2f} mm, v0 = {yd0:.3f} m/s; the "
            f"handout's model at the start of its line).",
        )
        out.update(
            {
                "handout_method": {
                    k: v for k, v in classic.items() if k not in ("curve", "points")
                },
                "fit": result.to_json(),
            }
        )
    c = lab.B_eq + B_emf
    doc.paragraph(
        f"Parameters for the rest of the lab (motor connected): B_eq from {lab.B_eq_source}."
    )
    doc.table(
        ["parameter", "value", "unit"],
        [
            ["m = M + M_J", f"{m:.4f}", "kg"],
            ["γ", f"{gamma:.4f}", "N/V"],
            ["B_emf", f"{B_emf:.4f}", "kg/s"],
            ["B_eq", f"{lab.B_eq:.4f}", "kg/s"],
            ["c = B_eq + B_emf", f"{c:.4f}", "kg/s"],
        ],
        numeric=[False, True, False],
    )
    lab.value("c", c, "kg/s", "c = B_eq + B_emf (Part (i))", "i")
    out.update(
        {
            "m": m,
            "gamma": gamma,
            "B_emf": B_emf,
            "B_eq": lab.B_eq,
            "c": c,
            "B_eq_source": lab.B_eq_source,
        }
    )
    lab.results["part_i"] = out


def _handout_b_eq(rec) -> dict:
    """B_eq by the handout's log-linear method (:func:`tuning.estimation.classic.loglinear_beq`),
    the
    ln|v| points and line it rests on, and the pure-viscous coast it implies."""
    from tuning.estimation.classic import loglinear_beq

    est = loglinear_beq(rec)
    d = est.details
    t0, t1 = d["start_time"], d["stop_time"]
    time = np.asarray(rec.time, dtype=float)
    y = np.asarray(rec.position, dtype=float)
    speed = np.abs(_smooth_velocity(y, float(rec.sample_time)))
    # ln|v| over the method's window and a little beyond, to show where the line bends.
    late = min(time[-1], t1 + 0.5 * (t1 - t0))
    shown = (time >= t0) & (time <= late) & (speed > 0)
    used = (time >= t0) & (time <= t1)
    slope = d["slope"]
    intercept = float(np.mean(np.log(speed[used]) - slope * (time[used] - t0)))
    # The viscous coast of the method: v = v0 e^{slope (t - t0)}, integrated from y(t0).
    k0 = int(np.argmin(np.abs(time - t0)))
    direction = np.sign(y[min(k0 + 10, y.size - 1)] - y[k0]) or 1.0
    tc = time[time >= t0]
    yc = y[k0] + direction * math.exp(intercept) * np.expm1(slope * (tc - t0)) / slope
    return {
        "B_eq": est.value,
        "stderr": est.stderr,
        "method": est.method,
        "start_time": t0,
        "stop_time": t1,
        "slope": slope,
        "intercept": intercept,
        "mass": d["mass"],
        "note": f"line through ln|v| over {t0:.3f} to {t1:.3f} s (speed above 10 % of "
        f"{d['start_speed']:.3f} m/s); pure viscous friction assumed",
        "points": (time[shown], np.log(speed[shown])),
        "curve": (tc, yc),
    }


def _smooth_velocity(y, sample_time, window=0.01):
    """Central differences [m/s] with a centred ``window`` [s] moving average (the handout's
    method differentiates the encoder counts; the average tames their steps)."""
    v = np.gradient(y, sample_time)
    w = max(1, int(round(window / sample_time)))
    padded = np.concatenate([np.full(w, v[0]), v, np.full(w, v[-1])])
    return np.convolve(padded, np.ones(w) / w, mode="same")[w:-w]


def _loglinear_figure(lab: Lab, classic: dict, source: str):
    from tuning.lab import figures

    t, lv = classic["points"]
    t0, t1 = classic["start_time"], classic["stop_time"]
    line_t = np.linspace(t0, t1, 50)
    line = classic["intercept"] + classic["slope"] * (line_t - t0)
    path, rel = lab.figure_path("part1_loglinear")
    figures.time_plot(
        path,
        [
            figures.Trace(t, lv, f"experiment: ln|v| ({source}, 10 ms average)", True),
            figures.Trace(
                line_t,
                line,
                f"least-squares line, slope {classic['slope']:.3f} 1/s "
                f"-> B_eq = −slope m = {classic['B_eq']:.3f} kg/s",
            ),
        ],
        ylabel="ln(|v| / (1 m/s))",
        title="Part (i): handout's method, ln|v| against t while the cart coasts",
        legend="lower left",
    )
    return rel


# ---------------------------------------------------------------- Part (ii)


def part_ii(lab: Lab) -> None:
    """P control k = 50 V/m, step 0.4 m: experiment vs simulations without and with
    saturation; B_eq re-estimated to fit the experiment."""
    import jaxcart as jc
    from jaxcart.plots import plot_runs, reference_run

    doc = lab.doc
    doc.heading("Part (ii): P control, k = 50 V/m, step of 0.4 m")
    rec = lab.recording("p_step")
    source = _source(lab, "p_step")
    controller = _controller(rec, jc.PID(kp=50.0, v_limit=V_SAT))
    horizon = 3.0
    exp = rec.experiment_for(horizon) if rec is not None else jc.step(0.4, horizon=horizon)
    amplitude = float(np.asarray(exp.signal)[-1])
    lab.say("Part (ii): simulations without and with saturation")
    sim_free = _exact(
        _plant_for(lab, rec, saturation=False, coulomb=False), _no_limit(controller), exp
    )
    sim_sat = _exact(_plant_for(lab, rec, coulomb=False), controller, exp)
    runs = [reference_run(sim_sat.time, sim_sat.reference)]
    if rec is not None:
        t, y, v = _crop(rec.time, rec.position, rec.command, horizon=horizon)
        runs.append(_run(f"experiment ({source})", t, y, v, role="experiment"))
    runs.append(
        _run(
            f"model without saturation (B_eq = {lab.B_eq:.3f} kg/s)",
            sim_free.time,
            sim_free.position,
            sim_free.command,
        )
    )
    runs.append(
        _run(
            f"model with saturation ±{V_SAT:g} V (B_eq = {lab.B_eq:.3f} kg/s)",
            sim_sat.time,
            sim_sat.position,
            sim_sat.command,
        )
    )
    if lab.f_c > 0:
        sim_c = _exact(_plant_for(lab, rec), controller, exp)
        runs.append(
            _run(
                f"model with saturation and Coulomb friction f_c = {lab.f_c:.3f} N",
                sim_c.time,
                sim_c.position,
                sim_c.command,
            )
        )
    out = {
        "recording": source,
        "controller": controller.to_dict(),
        "B_eq_model": lab.B_eq,
        "f_c_model": lab.f_c,
    }
    rows = []
    if rec is not None:
        lab.say(f"Part (ii): re-estimating B_eq to fit {source}")
        refit = _fit([rec], ("B_eq",), initial={"B_eq": lab.B_eq}, quick=True)
        b_ii = _estimate(refit, "B_eq")
        lab.value(
            "B_eq_p50",
            None if b_ii is None else b_ii.value,
            "kg/s",
            "B_eq re-estimated on Part (ii), handout model (no Coulomb)",
            "ii",
        )
        out["refit"] = refit.to_json()
        rows.append(
            [
                "B_eq re-estimated (handout model: saturation, no Coulomb friction)",
                _pm(b_ii, "kg/s"),
                mm(refit.rms_after_exact),
            ]
        )
        if b_ii is not None:
            sim_re = _exact(_plant_for(lab, rec, coulomb=False, B_eq=b_ii.value), controller, exp)
            runs.append(
                _run(
                    f"model with saturation, B_eq re-estimated = {b_ii.value:.3f} kg/s",
                    sim_re.time,
                    sim_re.position,
                    sim_re.command,
                )
            )
        if lab.f_c > 0:
            refit_c = _fit([rec], ("B_eq",), initial={"B_eq": lab.B_eq, "f_c": lab.f_c}, quick=True)
            b_ii_c = _estimate(refit_c, "B_eq")
            lab.value(
                "B_eq_p50_coulomb",
                None if b_ii_c is None else b_ii_c.value,
                "kg/s",
                f"B_eq re-estimated on Part (ii) with f_c = {lab.f_c:.3f} N held",
                "ii",
                true_key="B_eq",
            )
            rows.append(
                [
                    f"B_eq re-estimated with Coulomb friction f_c = {lab.f_c:.3f} N held "
                    f"({lab.f_c_source})",
                    _pm(b_ii_c, "kg/s"),
                    mm(refit_c.rms_after_exact),
                ]
            )
            out["refit_with_coulomb"] = refit_c.to_json()
        e_meas = float(amplitude - rec.position[-1])
        rows.append(["measured final error r − y(end)", mm(e_meas), ""])
        out["final_error_measured"] = e_meas
        best = b_ii_c if lab.f_c > 0 else b_ii
        best_rms = (refit_c if lab.f_c > 0 else refit).rms_after_exact
        out["B_eq_agreement"] = _b_eq_agreement(lab, best, best_rms)
    path, rel = lab.figure_path("part2_p50")
    plot_runs(
        runs,
        title=f"Part (ii): P control k = {controller.kp:g} V/m, step {amplitude:g} "
        f"m: position (top) and voltage (bottom)",
        path=path,
        v_limit=V_SAT,
    )
    info_free = jc.step_info(sim_free)
    info_sat = jc.step_info(sim_sat, v_limit=V_SAT)
    doc.paragraph(
        f"Simulations with the model of Part (i) (B_eq = {lab.B_eq:.3f} kg/s, no Coulomb "
        f"friction, as in the handout): without saturation the voltage starts at "
        f"k r = {controller.kp * amplitude:g} V and the cart settles in "
        f"{info_free.settling_time:.3f} s (overshoot {info_free.overshoot:.1f} %); with the "
        f"±{V_SAT:g} V saturation the voltage is clipped for {info_sat.saturation_time:.3f} s "
        f"and the cart settles in {info_sat.settling_time:.3f} s (overshoot "
        f"{info_sat.overshoot:.1f} %)."
        + (
            f" The full model adds the Coulomb friction f_c = {lab.f_c:.3f} N ({lab.f_c_source})."
            if lab.f_c > 0
            else ""
        )
    )
    if rows:
        doc.paragraph(
            "B_eq re-estimated so that the model fits this experiment (least "
            "squares on the position, checked on the exact simulator):"
        )
        doc.table(
            ["quantity", "value", "RMS position error (exact sim.)"],
            rows,
            numeric=[False, True, True],
        )
    agreement = out.get("B_eq_agreement")
    if agreement:
        (doc.paragraph if agreement["agree"] else doc.note)(agreement["text"])
    what = "experiment and simulations" if rec is not None else "simulations"
    doc.figure(
        rel,
        f"Part (ii): {what} without and with saturation, position and voltage over three seconds.",
    )
    out["simulations"] = {
        "without_saturation": info_free.as_dict(),
        "with_saturation": info_sat.as_dict(),
    }
    lab.results["part_ii"] = out


def _b_eq_agreement(lab: Lab, est, rms) -> dict | None:
    """Whether Part (ii)'s B_eq agrees with the tap's (within 2 combined standard errors or
    10 %), and the report's text on it (a note, pointing at the diagnosis, when not)."""
    if est is None or lab.B_eq_stderr is None:
        return None
    diff = abs(est.value - lab.B_eq)
    sigma = math.hypot(est.stderr, lab.B_eq_stderr)
    agree = diff <= 2 * sigma or diff <= 0.1 * lab.B_eq
    where = (
        "The [diagnosis](#diagnosis-what-the-model-leaves-out) below fits the effects the model "
        "may leave out to each recording and compares the B_eq they give."
        if lab.diagnosis
        else "`jaxcart diagnose` on both files (or this lab without --no-diagnosis) looks for "
        "the effects the model leaves out."
    )
    both = (
        f"B_eq from this step ({est.value:.3f} ± {fmt(est.stderr, 2)} kg/s) and from the tap "
        f"({lab.B_eq:.3f} ± {fmt(lab.B_eq_stderr, 2)} kg/s, {lab.B_eq_source})"
    )
    if agree:
        text = f"{both} agree ({diff / sigma:.1f} standard errors apart): one cart, one B_eq."
    else:
        text = (
            f"{both} disagree: {diff / sigma:.1f} standard errors apart, a factor "
            f"{max(est.value, lab.B_eq) / min(est.value, lab.B_eq):.2g}. One cart has one "
            f"viscous friction, so the model leaves out physics that the two experiments see "
            f"differently (here the motor is connected and driven, in the tap it is not), as "
            f"the fit's RMS error of {mm(rms)} also shows. The later parts keep the tap's "
            f"value. {where}"
        )
    return {
        "B_eq_tap": lab.B_eq,
        "B_eq_step": est.value,
        "standard_errors_apart": diff / sigma,
        "agree": agree,
        "text": text,
    }


# ---------------------------------------------------------------- Part (iii)


def part_iii(lab: Lab) -> None:
    """f_c from the ramp; the bound |e(inf)| <= f_c / (k gamma) for k = 10; measured and
    simulated e(inf)."""
    import jaxcart as jc

    doc = lab.doc
    doc.heading("Part (iii): Coulomb friction and the steady-state error")
    out = {"ramp": _ramp(lab), "p_control_bounds": _p_bounds(lab)}
    lab.value(
        "f_c", lab.f_c, "N", f"f_c used from here on ({lab.f_c_source})", "iii", true_key="f_c"
    )

    from tuning.lab import figures

    doc.heading("Steady-state error of P control, k = 10 V/m", 3)
    rec = lab.recording("p_error")
    source = _source(lab, "p_error")
    controller = _controller(rec, jc.PID(kp=10.0))
    k = float(controller.kp)
    exp = _experiment(rec, "p_error")
    lab.say("Part (iii): steady-state error, measured and simulated")
    plant = _plant_for(lab, rec)
    gamma = float(plant.gamma)  # the simulated loop's own gain (a plant file may scale it)
    bound = deadband.band(lab.f_c, k, gamma)
    sim = _exact(plant, controller, exp)
    sim_lin = _exact(_plant_for(lab, rec, coulomb=False), controller, exp)
    e_sim = _final_error(sim.time, sim.error)
    r_final = float(np.asarray(exp.signal)[-1])
    step = r_final - float(exp.y0)
    m, c = float(plant.m), float(plant.c)
    horizon = float(np.asarray(sim.time)[-1])
    # e(inf) is the mean over the last FINAL_WINDOW: the creep at its start bounds it.
    t_creep = max(0.0, horizon - FINAL_WINDOW)
    creep = deadband.creep(m, c, gamma, k, lab.f_c, step, t_creep)
    s_poles = deadband.poles(m, c, gamma, k)
    q = deadband.count_size(rec.position) if rec is not None else 0.0
    lab.value("e_bound", bound, "m", "dead band b = f_c / (k γ), k = 10 V/m", "iii")
    lab.value("e_inf_sim", e_sim, "m", "simulated e(inf), Coulomb + saturation", "iii")
    traces = []
    rows = [["dead band b = f_c / (k γ)", mm(bound, 4)]]
    if creep > 0:
        rows.append([f"still to creep at {t_creep:g} s (linear model, slower pole)", mm(creep, 2)])
    checks = []
    if rec is not None:
        e_rec = np.asarray(rec.reference) - rec.position
        e_meas = _final_error(rec.time, e_rec)
        lab.value("e_inf_measured", e_meas, "m", "measured e(inf)", "iii")
        traces.append(figures.Trace(rec.time, e_rec * 1e3, f"experiment ({source})", True))
        rows += [
            ["encoder count q (a recorded error reads up to q high)", mm(q, 4)],
            [
                f"measured e(inf) (mean of the last {FINAL_WINDOW:g} s of {rec.time[-1]:.1f} s)",
                mm(e_meas, 4),
            ],
            ["its stated bound b + creep + q", mm(bound + creep + q, 4)],
        ]
        checks.append(("measured", e_meas, bound + creep + q))
        out["e_inf_measured"] = e_meas
    rows += [
        ["simulated e(inf) (Coulomb friction + saturation, exact stick-slip)", mm(e_sim, 4)],
        ["its stated bound b + creep", mm(bound + creep, 4)],
    ]
    checks.append(("simulated", e_sim, bound + creep))
    traces.extend(_error_traces(sim, sim_lin, lab.f_c))
    path, rel = lab.figure_path("part3_error")
    top = max(3.0 * bound, 0.25 * abs(r_final)) * 1e3
    figures.time_plot(
        path,
        traces,
        ylabel="error e = r − y [mm]",
        title=f"Part (iii): P control k = {k:g} V/m, step {r_final:g} m: error (zoomed)",
        hlines=[
            (bound * 1e3, f"dead band ±f_c/(k γ) = ±{bound * 1e3:.2f} mm", {"linestyle": ":"}),
            (-bound * 1e3, None, {"linestyle": ":"}),
        ],
        ylim=(-1.5 * bound * 1e3, top),
        legend="upper right",
    )
    pole_text = " and ".join(f"{p.real:.3g}" for p in sorted(s_poles, key=lambda p: -p.real))
    if deadband.overdamped(m, c, gamma, k):
        approach = (
            f"Here the loop m s² + c s + k γ has real poles ({pole_text} 1/s): coming from one "
            f"side without overshoot, the cart creeps towards the edge of the band, its "
            f"distance from the edge falling as e^({sorted(s_poles.real)[-1]:.3g} t), and never "
            f"stops inside it in finite time; at the start of the last {FINAL_WINDOW:g} s of "
            f"the run (over which e(inf) is averaged, from {t_creep:g} s) it is "
            f"still {mm(creep, 2)} beyond the edge (linear model)."
        )
    else:
        approach = (
            "Here the loop m s² + c s + k γ has complex poles: the cart overshoots and sticks "
            "at a reversal inside the band."
        )
    doc.paragraph(
        f"With Coulomb friction the cart can rest only where the P controller's force k γ |e| "
        f"does not beat f_c: the dead band |e(inf)| ≤ b = f_c / (k γ) = {fmt(lab.f_c)} / "
        f"({k:g} × {gamma:.4f}) = {mm(bound, 4)}. {approach} The encoder reads whole counts "
        f"below the cart, so a recorded error can exceed the true one by up to one count q. "
        f"The bound that a run of finite length must meet is therefore b + creep (+ q when "
        f"recorded)."
    )
    doc.table(["quantity", "value"], rows, numeric=[False, True])
    verdicts = []
    for what, value, limit in checks:
        holds = abs(value) <= limit * (1 + 1e-9)
        verdicts.append({"what": what, "value": value, "bound": limit, "holds": holds})
        if not holds:
            implied = deadband.f_c_lower(value, k, gamma, q if what == "measured" else 0.0)
            doc.note(
                f"The {what} error {mm(value, 4)} is outside the stated bound {mm(limit, 4)}: "
                f"it implies f_c ≥ {implied:.4f} N, more than the {lab.f_c:.4f} N used "
                f"({lab.f_c_source}); that f_c is low for this experiment, or the cart is "
                f"still moving at the end."
            )
    if all(v["holds"] for v in verdicts):
        doc.paragraph(
            "Both errors lie within their stated bounds."
            if len(verdicts) > 1
            else "The simulated error lies within its stated bound."
        )
    what = "experiment and simulations" if rec is not None else "simulations"
    doc.figure(
        rel,
        f"Part (iii): error of P control, {what}, with the dead band ±f_c/(k γ) "
        f"dotted (the error starts at {r_final * 1e3:g} mm).",
    )
    out["bound_checks"] = verdicts
    out["creep"] = creep
    out["quantization"] = q
    out.update(
        {
            "recording": source,
            "k": k,
            "f_c": lab.f_c,
            "f_c_source": lab.f_c_source,
            "bound": bound,
            "e_inf_simulated": e_sim,
        }
    )
    lab.results["part_iii"] = out


def _ramp(lab: Lab) -> dict:
    """f_c from the 0.1 V/s ramp (handout's method and a fit), or a simulated ramp."""
    import jaxcart as jc
    from tuning.lab import figures

    doc = lab.doc
    gamma = float(jc.Plant().gamma)
    doc.heading("f_c from the voltage ramp (0.1 V/s)", 3)
    ramp = lab.recording("ramp")
    source = _source(lab, "ramp")
    out = {"recording": source}
    marks = []
    if ramp is not None:
        lab.say(f"Part (iii): f_c from {source} by the handout's method (breakaway)")
        classic = _handout_f_c(ramp)
        lab.say(f"Part (iii): fit of f_c to {source} (B_eq held at {lab.B_eq:.3f} kg/s)")
        result = _fit([ramp], ("f_c",), initial={"B_eq": lab.B_eq}, quick=True)
        f_fit = _estimate(result, "f_c")
        if f_fit is not None:
            lab.f_c, lab.f_c_source = f_fit.value, f"Part (iii), fit to the ramp {source}"
        else:
            lab.f_c, lab.f_c_source = classic["f_c"], f"Part (iii), handout's method on {source}"
        lab.value(
            "f_c_ramp_handout",
            classic["f_c"],
            "N",
            "f_c, handout's method (ramp breakaway)",
            "iii",
            true_key="f_c",
        )
        lab.value(
            "f_c_ramp_fit",
            None if f_fit is None else f_fit.value,
            "N",
            "f_c, fit to the ramp",
            "iii",
            true_key="f_c",
        )
        seg = result.segments[0]
        u = np.asarray(ramp.command if ramp.command is not None else ramp.experiment.signal)
        top = [
            figures.Trace(ramp.time, ramp.position * 1e3, f"experiment ({source})", True),
            figures.Trace(
                seg.time,
                np.asarray(seg.after_exact) * 1e3,
                f"model, fitted f_c = {fmt(lab.f_c, 4)} N",
            ),
        ]
        bottom = [figures.Trace(ramp.time, u, "voltage command v", True)]
        marks.append(
            (
                classic["voltage"],
                f"breakaway seen at {classic['voltage']:.4f} V (handout's method)",
                {"linestyle": ":"},
            )
        )
        doc.paragraph(
            "The cart stays put until the drive γ v exceeds the friction f_c: the handout "
            "reads f_c = γ v at the voltage where the cart starts to move. The fit instead "
            "simulates the whole ramp (stick, breakaway, acceleration) with B_eq from Part (i) "
            "and fits f_c to the positions."
        )
        doc.table(
            ["method", "f_c [N]", "notes"],
            [
                ["handout's method (breakaway)", f"{classic['f_c']:.4f}", classic["note"]],
                [
                    f"fit (B_eq = {lab.B_eq:.3f} kg/s held)",
                    _pm(f_fit, "").strip(),
                    f"RMS position error {mm(result.rms_after_exact)} (exact simulator)",
                ],
            ],
            numeric=[False, True, False],
        )
        out.update({"handout_method": classic, "fit": result.to_json()})
    else:
        doc.paragraph(
            f"The ramp below is simulated with f_c = {fmt(lab.f_c)} N from {lab.f_c_source}."
        )
        sim = _exact(lab.plant(), None, jc.voltage_ramp(0.1, horizon=HORIZON["ramp"]))
        top = [
            figures.Trace(
                sim.time, np.asarray(sim.position) * 1e3, f"simulation, f_c = {fmt(lab.f_c, 4)} N"
            )
        ]
        bottom = [figures.Trace(sim.time, np.asarray(sim.command), "voltage command v")]
    marks.append(
        (
            lab.f_c / gamma,
            f"f_c / γ = {lab.f_c / gamma:.4f} V",
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
        title=f"Part (iii): open-loop voltage ramp 0.1 V/s ({source})",
        bottom_hlines=marks,
    )
    doc.figure(
        rel,
        "Part (iii): the voltage ramp; the cart breaks away once γ v exceeds f_c "
        "(the voltage f_c/γ dashed).",
    )
    return out


def _p_bounds(lab: Lab) -> dict:
    """Bounds on f_c from the P-control recordings
    (:func:`tuning.estimation.classic.pcontrol_fc_bounds`):
    stuck at the end, γ k (|e(inf)| − q) <= f_c (one encoder count q off, see
    :mod:`tuning.lab.deadband`); wherever it started or reversed, f_c < γ |u|."""
    from tuning.estimation.classic import pcontrol_fc_bounds

    rows, out = [], {}
    for slot in ("p_error", "p_step"):
        rec = lab.recording(slot)
        if rec is None:
            continue
        name = Path(rec.path).name
        try:
            est = pcontrol_fc_bounds(rec)
        except UserError as exc:
            rows.append([name, "n/a", "n/a", str(exc)])
            continue
        d = est.details
        q = deadband.count_size(rec.position)
        pid = rec.controller
        lower = deadband.f_c_lower(d["e_inf"], float(pid.kp), d["gamma"], q, float(pid.v_limit))
        out[slot] = {**est.to_json(), "lower": lower, "lower_without_count": est.lower, "q": q}
        lab.value(
            f"f_c_lower_{slot}",
            lower,
            "N",
            f"f_c lower bound from the P-control steady state ({name})",
            "iii",
        )
        rows.append(
            [
                name,
                fmt(lower),
                fmt(est.upper),
                f"e(inf) = {mm(d['e_inf'])}, u(inf) = {d['u_inf']:.4f} V, q = {mm(q, 4)}",
            ]
        )
    if rows:
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
        outside = [
            Path(lab.recording(slot).path).name
            for slot, est in out.items()
            if (est["lower"] is not None and lab.f_c < (1 - BOUND_SLACK) * est["lower"])
            or (est["upper"] is not None and lab.f_c > (1 + BOUND_SLACK) * est["upper"])
        ]
        if outside:
            lab.doc.note(
                f"The f_c used ({lab.f_c:.3f} N, {lab.f_c_source}) is more than "
                f"{BOUND_SLACK:.0%} outside the bounds of {', '.join(outside)}: the friction "
                f"in that experiment differs from the model's."
            )
        out["outside_bounds"] = outside
    return out


def _handout_f_c(rec) -> dict:
    """f_c by the handout's ramp-breakaway method
    (:func:`tuning.estimation.classic.ramp_breakaway_fc`)."""
    from tuning.estimation.classic import ramp_breakaway_fc

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


# ---------------------------------------------------------------- Part (iv)


def part_iv(lab: Lab) -> None:
    """PI k = 10, k_i = 15 with Coulomb friction: simulated and measured error; the largest
    stable k_i and the root locus with the fitted parameters."""
    import jaxcart as jc
    from tuning.lab import figures, prelab

    doc = lab.doc
    doc.heading("Part (iv): PI control, k = 10 V/m, k_i = 15 V/(m s)")
    rec = lab.recording("pi")
    source = _source(lab, "pi")
    controller = _controller(rec, jc.PID(kp=10.0, ki=15.0))
    exp = _experiment(rec, "pi")
    lab.say("Part (iv): PI simulations")
    sim = _exact(_plant_for(lab, rec), controller, exp)
    sim_lin = _exact(_plant_for(lab, rec, coulomb=False), controller, exp)
    traces = []
    out = {"recording": source, "controller": controller.to_dict()}
    if rec is not None:
        e_rec = np.asarray(rec.reference) - rec.position
        traces.append(figures.Trace(rec.time, e_rec * 1e3, f"experiment ({source})", True))
        out["final_error_measured"] = _final_error(rec.time, e_rec)
        rms = float(np.sqrt(np.mean((np.asarray(sim.position) - rec.position) ** 2)))
        out["rms_difference"] = rms
        lab.value("pi_rms", rms, "m", "PI: RMS difference simulation − experiment", "iv")
    traces.extend(_error_traces(sim, sim_lin, lab.f_c))
    path, rel = lab.figure_path("part4_pi_error")
    r_final = float(np.asarray(exp.signal)[-1])
    figures.time_plot(
        path,
        traces,
        ylabel="error e = r − y [mm]",
        title=f"Part (iv): PI control k = {controller.kp:g} V/m, k_i = "
        f"{controller.ki:g} V/(m s), step {r_final:g} m: error",
        hlines=[(0.0, None, {"linewidth": 0.6})],
        legend="upper right",
    )
    doc.paragraph(
        "The integral term removes the steady-state error that Coulomb friction leaves under "
        "P control, but only slowly, and with stick-slip: the cart sticks, the integral "
        "winds up until γ v beats f_c, the cart slips, and may stick again on the other side "
        "(hunting)."
    )
    if rec is not None:
        doc.paragraph(
            f"RMS difference between the simulated and measured position: "
            f"{mm(out['rms_difference'])}; measured error at the end "
            f"{mm(out['final_error_measured'])}, simulated "
            f"{mm(_final_error(sim.time, sim.error))}."
        )
    what = "experiment and simulations" if rec is not None else "simulations"
    doc.figure(rel, f"Part (iv): error of PI control, {what}.")
    out["final_error_simulated"] = _final_error(sim.time, sim.error)

    doc.heading("Largest stable k_i with the fitted parameters", 3)
    plant = lab.plant()
    bound = prelab.routh_and_locus(
        lab,
        float(plant.m),
        float(plant.c),
        float(plant.gamma),
        float(controller.kp),
        name="part4_root_locus",
        part="iv",
        title=f"Part (iv): root locus, k = {controller.kp:g} V/m, B_eq = {lab.B_eq:.3f} kg/s",
        key="ki_max_fitted",
    )
    stable = controller.ki < bound["ki_max_routh"]
    shown = "simulated and measured error" if rec is not None else "simulated error"
    doc.paragraph(
        f"The PI gain k_i = {controller.ki:g} V/(m s) is {'inside' if stable else 'outside'} "
        f"the stable range of the linear model (small signals: the Routh bound does not "
        f"account for saturation, integrator windup or Coulomb friction, whose effect shows "
        f"in the {shown} above)."
    )
    out["pi_bound"] = bound
    lab.results["part_iv"] = out


# ---------------------------------------------------------------- Part (v)


def part_v(lab: Lab) -> None:
    """The PID design: simulated and measured position with the metrics of both; the slider
    moves simulated with the tuned gains."""
    import jaxcart as jc
    from jaxcart.plots import plot_runs, reference_run

    doc = lab.doc
    doc.heading("Part (v): the PID design")
    rec = lab.recording("pid")
    source = _source(lab, "pid")
    tuned = (
        lab.tuned.gains if lab.tuned is not None else jc.PID(kp=40.0, kd=5.0, ki=5.0, v_limit=V_SAT)
    )
    controller = _controller(rec, tuned)
    same = rec is None or _same_gains(controller, tuned)
    exp = _experiment(rec, "pid")
    plant = _plant_for(lab, rec)
    lab.say("Part (v): PID step, simulated and measured")
    sim = _exact(plant, controller, exp)
    info_sim = jc.step_info(sim, v_limit=V_SAT)
    runs = [reference_run(sim.time, sim.reference)]
    rows = []
    out = {"recording": source, "controller": controller.to_dict()}
    if rec is not None:
        runs.append(
            _run(f"experiment ({source})", rec.time, rec.position, rec.command, role="experiment")
        )
        info_rec = jc.step_info(rec.as_response(), v_limit=V_SAT)
        rows.append([f"measured ({source})"] + _metrics_row(info_rec))
        out["measured"] = info_rec.as_dict()
        for name in ("rise_time", "overshoot", "settling_time", "steady_state_error"):
            unit = {"overshoot": "%", "steady_state_error": "m"}.get(name, "s")
            lab.value(
                f"pid_measured_{name}",
                getattr(info_rec, name),
                unit,
                f"PID step, measured {name.replace('_', ' ')}",
                "v",
            )
    if rec is None:
        label = "simulated, tuned gains"
    else:
        label = "simulated, the recording's gains" if not same else "simulated, same gains"
    runs.append(_run(f"{label} (fitted model)", sim.time, sim.position, sim.command))
    rows.append([f"{label}, fitted model"] + _metrics_row(info_sim))
    out["simulated"] = info_sim.as_dict()
    for name in ("rise_time", "overshoot", "settling_time", "steady_state_error"):
        unit = {"overshoot": "%", "steady_state_error": "m"}.get(name, "s")
        lab.value(
            f"pid_simulated_{name}",
            getattr(info_sim, name),
            unit,
            f"PID step, simulated {name.replace('_', ' ')}",
            "v",
        )
    if not same:
        sim_t = _exact(plant, tuned, exp)
        info_t = jc.step_info(sim_t, v_limit=V_SAT)
        runs.append(
            _run(
                "simulated, pre-lab tuned gains (fitted model)",
                sim_t.time,
                sim_t.position,
                sim_t.command,
            )
        )
        rows.append(["simulated, pre-lab tuned gains, fitted model"] + _metrics_row(info_t))
        out["tuned_on_fitted_model"] = info_t.as_dict()
    path, rel = lab.figure_path("part5_pid_step")
    r_final = float(np.asarray(exp.signal)[-1])
    plot_runs(
        runs,
        title=f"Part (v): PID kp = {controller.kp:.4g} V/m, kd = {controller.kd:.4g} V s/m, "
        f"ki = {controller.ki:.4g} V/(m s); step {r_final:g} m",
        path=path,
        v_limit=V_SAT,
        band=SETTLING_BAND,
    )
    gains_text = (
        f"kp = {controller.kp:.4g} V/m, kd = {controller.kd:.4g} V s/m, "
        f"ki = {controller.ki:.4g} V/(m s), tau = {controller.tau:g} s"
    )
    if rec is None:
        whose = f"Gains simulated (the pre-lab's tuned PID): {gains_text}."
    elif same:
        whose = f"Gains of the experiment, the pre-lab's tuned PID: {gains_text}."
    else:
        whose = (
            f"Gains of the experiment: {gains_text}. These are **not** the pre-lab's tuned "
            f"gains (kp = {tuned.kp:.4g} V/m, kd = {tuned.kd:.4g} V s/m, ki = "
            f"{tuned.ki:.4g} V/(m s)), which the last row simulates on the same model."
        )
    doc.paragraph(
        f"{whose} The simulation uses the fitted model (B_eq = {lab.B_eq:.3f} kg/s, "
        f"f_c = {lab.f_c:.3f} N, ±6 V saturation) and the exact simulator. Design problem: "
        f"settling < 1 s, overshoot < 5 %."
    )
    doc.table(
        [
            "run",
            "rise time [s]",
            "overshoot [%]",
            "settling time [s]",
            "steady-state error [mm]",
            "meets design",
        ],
        rows,
        numeric=[False, True, True, True, True, False],
    )
    what = "experiment and simulations" if rec is not None else "simulation"
    doc.figure(rel, f"Part (v): PID step, {what}, position and voltage.")

    lab.say("Part (v): slider moves with the tuned gains")
    times, values = zip(*SLIDER, strict=True)
    exp_s = jc.setpoints(times, values, horizon=SLIDER_HORIZON)
    sim_s = _exact(lab.plant(), tuned, exp_s)
    moves = _slider_moves(sim_s, times)
    path, rel = lab.figure_path("part5_slider")
    plot_runs(
        [
            reference_run(sim_s.time, sim_s.reference, "slider (reference r)"),
            _run("simulated, tuned gains, fitted model", sim_s.time, sim_s.position, sim_s.command),
        ],
        title=f"Part (v): slider moves 0.2, 0, −0.2, 0.2 m\nkp = {tuned.kp:.4g} V/m, "
        f"kd = {tuned.kd:.4g} V s/m, ki = {tuned.ki:.4g} V/(m s)",
        path=path,
        v_limit=V_SAT,
    )
    doc.paragraph(
        "The slider moves of the handout (0.2 m, back to 0, −0.2 m, 0.2 m, one every "
        "2.5 s) simulated with the pre-lab's tuned gains on the fitted model:"
    )
    doc.table(
        [
            "move",
            "from [m]",
            "to [m]",
            "rise time [s]",
            "overshoot [%]",
            "settling time [s]",
            "error at the next move [mm]",
        ],
        [
            [
                str(i + 1),
                f"{a:g}",
                f"{b:g}",
                f"{info.rise_time:.3f}",
                f"{info.overshoot:.2f}",
                _seconds(info.settling_time),
                f"{info.steady_state_error * 1e3:.3g}",
            ]
            for i, (a, b, info) in enumerate(moves)
        ],
        numeric=[False, True, True, True, True, True, True],
    )
    failing = [
        (i + 1, info)
        for i, (_, _, info) in enumerate(moves)
        if not info.meets(SETTLING_SPEC, OVERSHOOT_SPEC)
    ]
    if failing:
        worst = max(info.overshoot for _, info in failing)
        slowest = max(info.settling_time for _, info in failing)
        why = []
        if worst >= OVERSHOOT_SPEC:
            why.append(f"overshoot up to {worst:.2f} %, above the {OVERSHOOT_SPEC:g} % allowed")
        if not slowest < SETTLING_SPEC:
            why.append(
                f"settling time up to {_seconds(slowest)} s, not under {SETTLING_SPEC:g} s"
                if math.isfinite(slowest)
                else f"a move that {_seconds(slowest)}"
            )
        doc.note(
            f"Move{'s' if len(failing) > 1 else ''} "
            + ", ".join(str(i) for i, _ in failing)
            + f" miss{'' if len(failing) > 1 else 'es'} the design problem ({'; '.join(why)}): "
            f"the gains were tuned on the handout's model (B_eq = {HANDOUT_B_EQ} kg/s, a 0.5 m "
            f"step) and these moves run on the fitted one (B_eq = {lab.B_eq:.3f} kg/s, "
            f"f_c = {lab.f_c:.3f} N) with 0.2 and 0.4 m steps. Retune on the fitted model "
            f"(`jaxcart tune --plant PLANT.toml`) or robustly (`jaxcart tune --robust`)."
        )
    doc.figure(rel, "Part (v): the slider moves simulated with the tuned gains.")
    out["slider"] = [{"from": a, "to": b, **info.as_dict()} for a, b, info in moves]
    out["slider_failing_moves"] = [i for i, _ in failing]
    lab.results["part_v"] = out


def _same_gains(a, b, rel: float = 5e-4) -> bool:
    """The same PID up to the 4 digits a file keeps (kp, kd, ki, tau)."""
    return all(
        math.isclose(float(getattr(a, n)), float(getattr(b, n)), rel_tol=rel, abs_tol=1e-9)
        for n in ("kp", "kd", "ki", "tau")
    )


def _seconds(x) -> str:
    """A time [s] for a table; a run that never settles says so instead of "inf"."""
    return f"{x:.3f}" if math.isfinite(x) else "does not settle within the horizon"


def _metrics_row(info) -> list[str]:
    return [
        f"{info.rise_time:.3f}",
        f"{info.overshoot:.2f}",
        _seconds(info.settling_time),
        f"{info.steady_state_error * 1e3:.3g}",
        "yes" if info.meets() else "no",
    ]


def _slider_moves(response, times):
    """Step metrics of each move of a piecewise-constant reference."""
    from jaxcart.metrics import step_info
    from jaxcart.smooth import Response

    t = np.asarray(response.time)
    bounds = [int(np.searchsorted(t, x - 1e-9)) for x in times] + [t.size]
    previous = float(response.position[0])
    moves = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        part = {f.name: getattr(response, f.name) for f in dataclasses.fields(Response)}
        for name in (
            "time",
            "position",
            "velocity",
            "reference",
            "error",
            "command",
            "voltage",
            "unlimited",
        ):
            if part.get(name) is not None:
                part[name] = np.asarray(part[name])[a:b]
        part["time"] = part["time"] - part["time"][0]
        target = float(np.asarray(response.reference)[a])
        moves.append((previous, target, step_info(Response(**part), v_limit=V_SAT)))
        previous = target
    return moves


def _error_traces(sim, sim_lin, f_c):
    """Simulated error [mm] with Coulomb friction and saturation, and without friction."""
    from tuning.lab import figures

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
