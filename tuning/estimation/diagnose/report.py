"""Drawing and writing a :class:`~tuning.estimation.diagnose.result.Diagnosis`: Markdown, figure,
JSON,
corrected plant file (nothing is written over an existing file without ``force``)."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np

from hw.atomicio import all_or_none, write_text
from hw.jsonio import write_json
from jaxcart import plots
from jaxcart.effects import REGISTRY
from jaxcart.errors import UserError
from jaxcart.plantspec import write_plant_file
from jaxcart.plots import EXPERIMENT_STYLE, figure_legend
from tuning.estimation.diagnose.crossval import WORSE
from tuning.estimation.diagnose.curve_report import curve_section, plot_curve, plot_track
from tuning.estimation.diagnose.policy import SIGNIFICANCE
from tuning.estimation.engine.parameters import at_edge


def _mm(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x * 1e3:.4f} mm"


def _two(x) -> str:
    """A standard error to two digits."""
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.2g}"


def _num(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.5g}"


def render_markdown(d, figure: str | None = None, curve_files: dict | None = None) -> str:
    """The diagnosis as a Markdown section (for ``report.md`` and the lab report);
    ``curve_files``: {"figure", "track_figure", "plant"} of the friction curves' outputs,
    where written."""
    lines = [f"# Diagnosis of {', '.join(d.recordings)}", "", f"**{d.verdict}**", ""]
    if d.controller_checks:
        lines += ["## Controller check", ""]
        lines += [f"- {c['message']}" for c in d.controller_checks]
        lines.append("")
    if d.status != "diagnosed":
        return "\n".join(lines + [f"- {m}" for m in d.messages]) + "\n"
    lines += _caveats(d) + _fit_section(d) + _per_recording_section(d) + _where_section(d)
    lines += _candidates_section(d, figure)
    lines += curve_section(d, curve_files)
    return "\n".join(lines) + "\n"


def _caveats(d) -> list:
    """Not explained, M and gamma_scale not told apart, implausible values."""
    lines = []
    if not d.explained:
        lines += ["## Not explained", "", d.misfit[:1].upper() + d.misfit[1:] + ".", ""]
        if d.suggestions:
            lines += ["What may be missing:", ""] + [f"- {s}" for s in d.suggestions] + [""]
    if d.unidentifiable:
        u = d.unidentifiable
        lines += [
            "## M and gamma_scale",
            "",
            u["note"][:1].upper() + u["note"][1:] + ".",
            "",
            "| structure | values | exact RMS |",
            "|---|---|---|",
        ]
        for alt in u["alternatives"]:
            values = ", ".join(f"{k} = {_num(v)}" for k, v in alt["values"].items())
            lines.append(f"| {alt['structure']} | {values} | {_mm(alt['rms'])} |")
        lines.append("")
    if d.implausible:
        lines += ["## Implausible values", ""] + [f"- {x}" for x in d.implausible] + [""]
    return lines


def _fit_section(d) -> list:
    """The fit on the exact simulator and the fitted parameters."""
    ratio = d.rms_before / d.rms_after if d.rms_after > 0 else math.inf
    lines = [
        "## Fit on the exact simulator",
        "",
        "| | RMS position error |",
        "|---|---|",
        f"| baseline (handout model, B_eq fitted) | {_mm(d.rms_before)} |",
        f"| corrected ({d.chosen}) | {_mm(d.rms_after)} |",
        f"| encoder floor q/sqrt(12) | {_mm(d.floor)} |",
    ]
    if d.repeat is not None:
        lines.append(f"| what the cart repeats (repeated runs) | {_mm(d.repeat)} |")
    lines += [
        "",
        f"Improvement: {ratio:.1f}x. Baseline B_eq = {_num(d.baseline['B_eq']['value'])} +/- "
        f"{_num(d.baseline['B_eq']['stderr'])} kg/s."
        + (f" What is left: {d.remainder}." if d.remainder else ""),
        "",
        "## Fitted parameters",
        "",
        "| parameter | value | standard error | unit | note |",
        "|---|---|---|---|---|",
    ]
    for n, p in d.parameters.items():
        note = []
        if p.get("settled") is False:
            lo, hi = p["range"]
            note.append(f"not settled: {_num(lo)} to {_num(hi)} (M or gamma_scale)")
        if p.get("stderr_widened"):
            note.append("widened for model error")
        edge = _edge(n, p["value"])
        if edge is not None:
            note.append(f"at the {edge[0]} edge of its range ({_num(edge[1])}): no estimate")
        z = d.significance.get(n)
        if z is None:  # a parameter of an effect: the effect's z (0.0 is a value)
            z = d.significance.get(_item_of(n))
        if z is not None:
            note.append(f"z = {z:.3g}")
        lines.append(
            f"| {n} | {_num(p['value'])} | {_num(p['stderr'])} | {p['unit']} | {'; '.join(note)} |"
        )
    if d.not_significant:
        lines += [
            "",
            "Not named, though in a structure that scored better (significance needs "
            f"z > {_significance()} and no parameter at a bound):",
            "",
        ]
        lines += [f"- {x['effect']} of {x['structure']}: {x['why']}" for x in d.not_significant]
    return lines


def _per_recording_section(d) -> list:
    """Each recording's own drive values and RMS (a joint diagnosis)."""
    if len(d.per_recording) < 2:
        return _cross_validation_lines(d.cross_validation)
    lines = [
        "",
        "## Each recording",
        "",
        "| recording | kind | own values | RMS before | RMS after | predicted, held out |",
        "|---|---|---|---|---|---|",
    ]
    for name, rec in d.per_recording.items():
        own = ", ".join(
            f"{n} = {_num(p['value'])} +/- {_num(p['stderr'])} {p['unit']}"
            + ("" if p.get("acts", True) else " (above what the run drove: does not act)")
            for n, p in rec["parameters"].items()
        )
        predicted = _mm(rec.get("predicted_rms"))
        if rec.get("held_out") is False:
            predicted += " (joint values)"
        lines.append(
            f"| {name} | {rec['kind']} | {own or '-'} | {_mm(rec['rms_before'])} | "
            f"{_mm(rec['rms_after'])} | {predicted} |"
        )
    return lines + _cross_validation_lines(d.cross_validation) + _driven_alone_lines(d)


def _driven_alone_lines(d) -> list:
    """The cart's values from the taps alone and from the driven runs alone beside the joint
    ones (with both): whether the recordings agree on one cart."""
    lines = []
    for alone, what in ((d.taps_alone, "the taps"), (d.driven_alone, "the driven runs")):
        if not alone or not alone["parameters"]:
            continue
        each = ", ".join(
            f"{n} = {_num(p['value'])} +/- {_num(p['stderr'])} {p['unit']} (jointly "
            f"{_num(d.parameters[n]['value'])})"
            for n, p in alone["parameters"].items()
            if n in d.parameters
        )
        lines += [
            "",
            f"Fitted on {what} alone ({', '.join(alone['recordings'])}; their own values free "
            f"too), the structure gives {each}, at {_mm(alone['rms'])} RMS over those runs.",
        ]
    return lines


def _cross_validation_lines(cv) -> list:
    """What the held-out column means, and what it says."""
    if not cv:
        return []

    text = (
        f"Held out ({cv['method']}): the cart's values ({', '.join(cv['refitted'])}) re-fitted "
        "without what is held out (one Gauss-Newton step from the joint values on the exact "
        "simulator)"
    )
    if cv["own"]:
        text += f", each run's own {', '.join(cv['own'])} and a tap's start state fitted to it"
    text += (
        "; what is held out is predicted with them and judged against what that experiment "
        "repeats, or without a repeat against 3 times its encoder floor. A part is named only "
        "where it improves this prediction."
    )
    lines = ["", text]
    for f in cv["folds"]:
        if not f["held_out"]:
            lines += ["", f"{f['recording']} is not held out ({f['why']}): the joint values."]
    ratio = cv["ratio"]
    if math.isfinite(ratio):
        times = f"{ratio:.2g}" if ratio < 10 else f"{ratio:.0f}"
        why = ""
        if ratio > WORSE:
            why = (
                ": the cart's values depend on which recordings are fitted, so something "
                "varies from run to run that the structure does not have"
            )
        lines += [
            "",
            f"Over what was held out: fitted {_mm(cv['fitted_rms'])}, predicted "
            f"{_mm(cv['predicted_rms'])} ({times}x the fit){why}.",
        ]
    return lines


def _where_section(d) -> list:
    """Where the recording and the baseline part, and the baseline's residual tests."""
    lines = ["", "## Where the recording and the baseline part", ""]
    if d.windows:
        lines += [
            "| recording | start [s] | end [s] | regime | share | RMS |",
            "|---|---|---|---|---|---|",
        ]
        for w in d.windows[:12]:
            lines.append(
                f"| {w['recording']} | {w['start']:.3f} | {w['end']:.3f} | {w['regime']} | "
                f"{w['share'] * 100:.1f} % | {_mm(w['rms'])} |"
            )
    else:
        lines.append("No window: the baseline residual stays within the encoder's quantization.")
    lines += ["", "## Residual tests (baseline)", ""]
    t = d.tests
    wh = t.get("whiteness", {})
    lines.append(
        f"- whiteness: lag-1 autocorrelation {wh.get('lag1_autocorrelation')}, Ljung-Box Q(20) "
        f"{wh.get('ljung_box_q20')} ({'white' if wh.get('white') else 'not white'})"
    )
    for k in ("command", "sign_velocity", "position", "acceleration"):
        if k in t:
            x = t[k]
            sig = "significant" if x["significant"] else "not significant"
            lines.append(
                f"- correlation with {k.replace('_', ' ')}: {x['correlation']:+.3f} (z = "
                f"{x['z']:+.1f}, {sig}; can explain: {', '.join(x['points_to'])})"
            )
    return lines


def _candidates_section(d, figure) -> list:
    """Every candidate tried, the figure and the corrected plant."""
    lines = [
        "",
        "## Candidates (fitted through the smoothed simulator, scored on the exact one)",
        "",
        "| structure | round | exact RMS | score | window evidence | significant | values "
        "(+/- standard error, SI) |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in d.candidates:
        sig = "yes" if not c.why_not else "no: " + c.why_not
        if not c.parts:
            sig = "-"
        lines.append(
            f"| {c.name} | {c.round} | {_mm(c.rms_exact)} | {c.score:.1f} | "
            f"{c.window_evidence * 100:.1f} % | {sig} | {_values_text(c.result)} |"
        )
    if figure:
        lines += ["", f"![recording, baseline and corrected model]({figure})"]
    if d.plant_file:
        lines += ["", f"Corrected plant: `{d.plant_file}` (for simulate, fit, tune, lab --plant)."]
    elif d.status == "diagnosed" and d.implausible:
        lines += [
            "",
            "No corrected plant file is written: a value above is outside what a cart of this "
            "lab has, and other commands would use it.",
        ]
    return lines


def _values_text(fit) -> str:
    """A structure's shared values with their standard errors, and how many it fits per run."""
    if fit is None:
        return "-"
    shared = [
        f"{n} {_num(e.value)} +/- {_two(e.stderr)}" for n, e in fit.params.items() if "@" not in n
    ]
    own = sum("@" in n for n in fit.params)
    return ", ".join(shared + ([f"{own} per run"] if own else []))


def _edge(name: str, value) -> tuple[str, float] | None:
    """(side, bound) where a fitted value sits on an edge of its range (engine.parameters)."""
    try:
        return at_edge(name, value) if value is not None and math.isfinite(value) else None
    except KeyError:  # a name the engine has no range for
        return None


def _item_of(name: str) -> str:
    """The significance item of a strength parameter (the Markdown's z column): the effect that
    declares it, for a parameter that has a neutral value."""
    for effect, cls in REGISTRY.items():
        for p in cls.params:
            if p.name == name and p.neutral is not None and not p.size:
                return effect
    return ""


def _significance() -> str:
    return f"{SIGNIFICANCE:g}"


#: The title's most lines; a headline longer than they hold ends in an ellipsis.
TITLE_LINES = 3


def figure_title(d, width: int = 95) -> str:
    """The figure's title: :attr:`~.result.Diagnosis.headline`, wrapped to ``width``
    characters a line, at most :data:`TITLE_LINES` lines (the last then ends in "...")."""
    return textwrap.fill(d.headline, width, max_lines=TITLE_LINES, placeholder=" ...")


def _title_width(fig, fontsize: float) -> int:
    """About how many characters of ``fontsize`` [pt] a line across ``fig`` holds (an average
    character of a sans-serif font is about 0.55 em wide; 0.6 leaves a margin)."""
    return max(60, int(fig.get_figwidth() * 72 / (0.6 * fontsize)))


def plot_diagnosis(d, path) -> Path:
    """Recording, baseline and corrected model above, residuals below; saved at ``path`` (its
    suffix sets the format: .png, .svg, .pdf). The mismatch of the baseline is shaded between
    it and the recording, the encoder floor is a grey band around zero residual, and the
    located windows are a strip along the time axis, each in the legend below the axes."""
    # lazy: matplotlib.figure costs 0.3-0.6 s at start-up (python -X importtime); its object
    # API sets no process state (no pyplot figure, no backend switched)
    from matplotlib.figure import Figure

    n = max(len(d.traces), 1)
    fig = Figure(figsize=(6.5 * n, 6.6), layout="constrained")
    axes = fig.subplots(2, n, squeeze=False, sharex="col")
    # One label per model, the same in both panels, so the legend names each once.
    corrected = f"corrected ({d.chosen})"
    for i, tr in enumerate(d.traces):
        top, bottom = axes[0, i], axes[1, i]
        t, measured = np.asarray(tr["time"]), np.asarray(tr["measured"])
        top.plot(t, measured, label="recording", **EXPERIMENT_STYLE)
        top.plot(t, tr["baseline"], "C0-", lw=1, label="baseline", zorder=3)
        top.plot(t, tr["after"], "C3--", lw=1, label=corrected, zorder=3)
        floor = d.floor if math.isfinite(d.floor) else 0.0
        top.fill_between(
            t,
            measured,
            tr["baseline"],
            where=np.abs(np.asarray(tr["baseline"]) - measured) > floor,
            color="orange",
            alpha=0.35,
            lw=0,
            label="mismatch of the baseline (beyond the floor)",
        )
        bottom.plot(t, (tr["baseline"] - measured) * 1e3, "C0-", lw=0.8, label="baseline")
        bottom.plot(t, (tr["after"] - measured) * 1e3, "C3--", lw=0.8, label=corrected)
        if math.isfinite(d.floor) and d.floor > 0:
            bottom.axhspan(
                -d.floor * 1e3,
                d.floor * 1e3,
                color="0.75",
                alpha=0.6,
                lw=0,
                zorder=0,
                label=f"encoder floor ±{d.floor * 1e3:.2g} mm",
            )
        for w in (w for w in d.windows if w["recording"] == tr["name"]):
            bottom.axvspan(
                w["start"],
                w["end"],
                ymin=0,
                ymax=0.04,
                color="orange",
                lw=0,
                label="windows beyond the floor (report's table)",
            )
        top.set_title(tr["name"])
        top.set_ylabel("position [m]")
        bottom.set_ylabel("residual model − recording [mm]")
        bottom.set_xlabel("time [s]")
    # Two columns a recording's width holds; four from two recordings on.
    figure_legend(fig, list(axes.flat), ncols=2 if n == 1 else 4)
    title = figure_title(d, _title_width(fig, 9))
    fig.suptitle(title, fontsize=9, color="black" if d.explained else "darkred")
    return plots.save(fig, path, dpi=110)


def write_outputs(d, out_dir, *, json_path=None, force: bool = False, fmt: str = "png") -> dict:
    """Write report.md, diagnosis.FMT (fmt: "png", "svg" or "pdf"), corrected_plant.toml (and
    the JSON) into ``out_dir``; refuses to overwrite any of them without ``force``. Returns
    {what: path}."""
    out = Path(out_dir)
    paths = {
        "report": out / "report.md",
        "figure": out / f"diagnosis.{fmt}",
        "plant_file": out / "corrected_plant.toml",
    }
    if d.status != "diagnosed":
        paths = {"report": out / "report.md"}
    elif d.implausible:
        # A value a cart of this lab does not have is never handed to other commands.
        del paths["plant_file"]
    if d.status == "diagnosed" and d.friction_curve.get("sides"):
        paths["curve_figure"] = out / f"friction_curve.{fmt}"
    if d.status == "diagnosed" and "track" in d.friction_curve:
        paths["track_figure"] = out / f"friction_track.{fmt}"
    if {"curve_figure", "track_figure"} & set(paths) and d.curve_plant is not None:
        paths["curve_plant"] = out / "curve_plant.toml"
    if json_path:
        paths["json"] = Path(json_path)
    for p in paths.values():
        if p.exists() and not force:
            raise UserError(f"{p} exists; choose another --out/--json or pass --force")

    with all_or_none(*paths.values()):  # a full disk at the last file leaves none of them
        _write_outputs(d, out, paths, json_path, force)
    return {k: str(v) for k, v in paths.items()}


def _write_outputs(d, out, paths, json_path, force) -> None:
    out.mkdir(parents=True, exist_ok=True)
    if d.status == "diagnosed":
        fit = {
            "source": "jaxcart diagnose",
            "recordings": ", ".join(d.recordings),
            "left_out": ", ".join(d.left_out) or "nothing",
            "rms_before": float(d.rms_before),
            "rms_after": float(d.rms_after),
        }
        for n, p in d.parameters.items():
            if math.isfinite(p["stderr"]):
                fit[f"stderr_{n}"] = float(p["stderr"])
        if "plant_file" in paths:
            write_plant_file(paths["plant_file"], d.plant, fit=fit, force=force)
            d.plant_file = str(paths["plant_file"])
        plot_diagnosis(d, paths["figure"])
    curve_files = {}
    if "curve_figure" in paths:
        curve_files["figure"] = plot_curve(d, paths["curve_figure"]).name
    if "track_figure" in paths:
        curve_files["track_figure"] = plot_track(d, paths["track_figure"]).name
    if "curve_plant" in paths:
        fit = {"source": "jaxcart diagnose --curve", "recordings": ", ".join(d.recordings)}
        write_plant_file(paths["curve_plant"], d.curve_plant, fit=fit, force=force)
        curve_files["plant"] = paths["curve_plant"].name
    figure = paths["figure"].name if d.status == "diagnosed" else None
    text = render_markdown(d, figure=figure, curve_files=curve_files)
    write_text(paths["report"], text, force=True)
    if json_path:
        write_json(paths["json"], d.to_json(), force=True)  # checked above
