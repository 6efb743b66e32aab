"""Part (i): B_eq from the tap test, by the handout's log-linear method and by a full fit.

:func:`compute` returns a :class:`TapResult` (the numbers, the fit and the improved
:class:`~tuning.lab.model.CartModel`); :func:`render` writes the section and its figures.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

import jaxcart as jc
from jaxcart.errors import UserError
from tuning.estimation.classic import loglinear_beq
from tuning.lab import figures, fits
from tuning.lab.context import HANDOUT_B_EQ, fmt, mm, value
from tuning.lab.model import CartModel, render_source, source_name


@dataclass(frozen=True, eq=False)
class TapResult:
    """Part (i)'s answers. recording: the tap (None: no tap, the model is unchanged);
    classic: the handout's method (:func:`handout_b_eq`), fit: the full fit of B_eq and f_c
    (None without a tap); model: the cart after this part; nominal: m [kg], gamma [N/V],
    B_emf [kg/s] of the appendix."""

    recording: object
    classic: dict | None
    fit: object
    model: CartModel
    nominal: dict = field(default_factory=dict)

    @property
    def source(self) -> str:
        return source_name(self.recording)

    @property
    def b_fit(self):
        return None if self.fit is None else fits.estimate(self.fit, "B_eq")

    @property
    def f_fit(self):
        return None if self.fit is None else fits.estimate(self.fit, "f_c")

    @property
    def c(self) -> float:
        """c = B_eq + B_emf [kg/s], motor connected."""
        return self.model.B_eq + self.nominal["B_emf"]


def compute(rec, start: CartModel, *, fit=fits.fit, say=lambda text: None) -> TapResult:
    """B_eq (and f_c) from the tap ``rec`` (None: keep ``start``); ``fit``: the fitter."""
    p = jc.Plant()
    nominal = {"m": float(p.m), "gamma": float(p.gamma), "B_emf": float(p.B_emf)}
    if rec is None:
        return TapResult(None, None, None, start, nominal)
    source = source_name(rec)
    say(f"Part (i): B_eq from {source} by the handout's method (log-linear)")
    classic = handout_b_eq(rec)
    say(f"Part (i): full fit of B_eq and f_c to {source} (smooth simulator, Levenberg-Marquardt)")
    result = fit([rec], ("B_eq", "f_c"))
    b_fit, f_fit = fits.estimate(result, "B_eq"), fits.estimate(result, "f_c")
    if b_fit is None:
        raise UserError(
            f"{rec.path}: B_eq cannot be determined from this tap recording "
            f"({result.params['B_eq'].note}); record a longer coast"
        )
    where = f"Part (i), full fit to {source}"
    model = dataclasses.replace(
        start, B_eq=b_fit.value, B_eq_source=where, B_eq_stderr=b_fit.stderr
    )
    if f_fit is not None:
        model = dataclasses.replace(model, f_c=f_fit.value, f_c_source=where)
    return TapResult(rec, classic, result, model, nominal)


def values(r: TapResult) -> list:
    out = []
    if r.recording is not None:
        f_fit = r.f_fit
        out += [
            value(
                "B_eq_tap_handout",
                r.classic["B_eq"],
                "kg/s",
                "B_eq, handout's log-linear method (tap)",
                "i",
                true_key="B_eq",
            ),
            value(
                "B_eq_tap_fit",
                r.b_fit.value,
                "kg/s",
                "B_eq, full fit to the tap",
                "i",
                true_key="B_eq",
            ),
            value(
                "f_c_tap_fit",
                None if f_fit is None else f_fit.value,
                "N",
                "f_c, full fit to the tap",
                "i",
                true_key="f_c",
            ),
        ]
    return out + [value("c", r.c, "kg/s", "c = B_eq + B_emf (Part (i))", "i")]


def to_json(r: TapResult) -> dict:
    out = {"recording": r.source}
    if r.recording is not None:
        out["handout_method"] = {k: v for k, v in r.classic.items() if k not in ("curve", "points")}
        out["fit"] = r.fit.to_json()
    return {
        **out,
        **r.nominal,
        "B_eq": r.model.B_eq,
        "c": r.c,
        "B_eq_source": r.model.B_eq_source,
    }


# ---------------------------------------------------------------- the handout's method


def handout_b_eq(rec) -> dict:
    """B_eq by the handout's log-linear method (:func:`tuning.estimation.classic.loglinear_beq`),
    the ln|v| points and line it rests on, and the pure-viscous coast it implies."""
    est = loglinear_beq(rec)
    d = est.details
    t0, t1 = d["start_time"], d["stop_time"]
    time = np.asarray(rec.time, dtype=float)
    y = np.asarray(rec.position, dtype=float)
    speed = np.abs(smooth_velocity(y, float(rec.sample_time)))
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


def smooth_velocity(y, sample_time, window=0.01):
    """Central differences [m/s] with a centred ``window`` [s] moving average (the handout's
    method differentiates the encoder counts; the average tames their steps)."""
    v = np.gradient(y, sample_time)
    w = max(1, int(round(window / sample_time)))
    padded = np.concatenate([np.full(w, v[0]), v, np.full(w, v[-1])])
    return np.convolve(padded, np.ones(w) / w, mode="same")[w:-w]


# ---------------------------------------------------------------- render


def render(lab, r: TapResult) -> None:
    """Part (i)'s section: both methods, their figures, the parameters for the rest."""
    doc = lab.doc
    doc.heading("Part (i): B_eq from the tap test")
    render_source(doc, r.recording, "tap")
    if r.recording is None:
        doc.paragraph(
            f"Without a tap recording B_eq stays at the handout's estimate "
            f"{HANDOUT_B_EQ} kg/s and the model has no Coulomb friction."
        )
    else:
        _render_methods(lab, r)
    doc.paragraph(
        f"Parameters for the rest of the lab (motor connected): B_eq from {r.model.B_eq_source}."
    )
    n = r.nominal
    doc.table(
        ["parameter", "value", "unit"],
        [
            ["m = M + M_J", f"{n['m']:.4f}", "kg"],
            ["γ", f"{n['gamma']:.4f}", "N/V"],
            ["B_emf", f"{n['B_emf']:.4f}", "kg/s"],
            ["B_eq", f"{r.model.B_eq:.4f}", "kg/s"],
            ["c = B_eq + B_emf", f"{r.c:.4f}", "kg/s"],
        ],
        numeric=[False, True, False],
    )


def _render_methods(lab, r: TapResult) -> None:
    doc, classic, result = lab.doc, r.classic, r.fit
    doc.paragraph(
        f"**Handout's method.** While the cart coasts with viscous friction only, "
        f"v(t) = v0 e^(−(B_eq/m) t): a least-squares line through ln|v| against t has the "
        f"slope −B_eq/m. Here the slope is {classic['slope']:.4f} 1/s, so B_eq = −slope × m "
        f"= {-classic['slope']:.4f} × {classic['mass']:.4f} kg = "
        f"**{classic['B_eq']:.4f} kg/s** (regression standard error "
        f"{fmt(classic['stderr'], 2)} kg/s; m = M + M_J, the motor's rotor still turns)."
    )
    doc.figure(
        _loglinear_figure(lab, classic, r.source),
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
    seg = result.segments[0]
    rows = [
        [
            "handout's method (log-linear)",
            f"{classic['B_eq']:.4f}",
            "not modelled",
            classic["note"],
        ],
        [
            "full fit (exact-simulator check)",
            fits.pm(r.b_fit, "").strip(),
            fits.pm(r.f_fit, "").strip(),
            f"RMS position error {mm(result.rms_after_exact)} over {seg.time[0]:.3f} to "
            f"{seg.time[-1]:.3f} s",
        ],
    ]
    doc.table(
        ["method", "B_eq [kg/s]", "f_c [N]", "notes"], rows, numeric=[False, True, True, False]
    )
    yd0, y0 = seg.nuisance["yd0"].value, seg.nuisance["y0"].value
    doc.figure(
        _tap_figure(lab, r),
        f"Part (i): the tap recording and both models over the coast (the full "
        f"fit starts at y0 = {y0 * 1e3:.2f} mm, v0 = {yd0:.3f} m/s; the "
        f"handout's model at the start of its line).",
    )


def _tap_figure(lab, r: TapResult) -> str:
    rec, classic, seg = r.recording, r.classic, r.fit.segments[0]
    b_fit, f_fit = r.b_fit, r.f_fit
    t_c, y_c = classic["curve"]
    traces = [
        figures.Trace(rec.time, rec.position * 1e3, f"experiment ({r.source})", True),
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
        title=f"Part (i): tap test, motor unplugged ({r.source})",
        xlim=(max(0.0, seg.time[0] - pad), min(rec.time[-1], seg.time[-1] + pad)),
    )
    return rel


def _loglinear_figure(lab, classic: dict, source: str) -> str:
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
    )
    return rel
