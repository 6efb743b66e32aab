"""``run_lab``: the whole pre-lab and lab report, from the built-in example recordings or from a
folder of real ones.

    data folder --find_inputs--> which recording is which part (lab.toml or a guess)
        |
        v
    compute: each part a function of its inputs, returning a frozen result
        pre-lab ------------------------------------------------ tuned gains --+
        tap --Part (i)--> model --+--Part (ii)--> B_eq agreement               |
                                  +--Part (iii)--> model (f_c) --+--Part (iv)  |
                                                                 +--Part (v) <-+
        |                                                        (progress on stderr)
        v
    render: each result drawn into its section, figures/NAME.png|svg|pdf, summary
        |
        v
    REPORT_DIR/report.md, report.html (figures embedded), results.json (and .mat), gains.json,
    figures/

>>> out = run_lab(out="/tmp/jaxcart-lab-demo", force=True)     # doctest: +SKIP
>>> sorted(p.name for p in out.iterdir())                        # doctest: +SKIP
['figures', 'gains.json', 'report.html', 'report.md', 'results.json', 'results.mat']
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import jax

from hw.atomicio import OutputError, describe, missing_folders, remove_empty
from hw.gains import write_gains
from hw.jsonio import to_jsonable, write_json
from jaxcart.background import Background
from jaxcart.errors import UserError
from jaxcart.matfile import write_mat_report
from jaxcart.plantspec import describe_plant
from tuning.lab import (
    cart,
    fits,
    part_i,
    part_ii,
    part_iii,
    part_iii_render,
    part_iv,
    part_v,
    part_v_design,
    part_v_render,
    prelab,
)
from tuning.lab import diagnosis as diagnosis_section
from tuning.lab.context import Lab, check_format, fmt, relative_error
from tuning.lab.data import ENCODER_PARAM, builtin_dir
from tuning.lab.html import Document
from tuning.lab.inputs import SLOTS, find_inputs, write_used
from tuning.lab.model import CartModel

DEFAULT_OUT = Path("jaxcart-lab")
#: Prefix of the hidden staging folder the report is written into before it is renamed.
STAGING_PREFIX = "."
TITLE = "Position control of the IP02 cart: pre-lab and lab report"


def output_dir(out=None, *, force: bool = False) -> Path:
    """The report folder, checked but not created: ``out`` (refused if it is a file, or a
    folder that holds files unless ``force``), or ./jaxcart-lab, or the first free
    ./jaxcart-lab-N. The report is written by :func:`staged` and appears there complete."""
    if out is None:
        path, n = DEFAULT_OUT, 1
        while path.exists():
            n += 1
            path = DEFAULT_OUT.with_name(f"{DEFAULT_OUT.name}-{n}")
        return path
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise UserError(f"--out {path}: a file of that name exists; give a folder name")
    if path.is_dir() and any(path.iterdir()) and not force:
        raise UserError(
            f"--out {path}: the folder exists and is not empty; choose another "
            f"name or pass --force to overwrite its report"
        )
    return path


@contextlib.contextmanager
def staged(final: Path):
    """Write into a hidden sibling ``.NAME.partial-PID/`` (yielded, figures/ made) and move it
    to ``final`` when the block completes; on any error or interrupt it is removed, so an
    interrupted lab leaves nothing that blocks a rerun. Into an existing, non-empty ``final``
    (``--force``) only the report's own files and figures/ are replaced; other files stay."""
    final = Path(final)
    parent = final.parent
    made = missing_folders([final])  # removed again, empty, if the report is not written
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(
            f"--out {final}: cannot create its folder {parent} ({exc.strerror or exc}); "
            f"choose a folder you can write to"
        ) from None
    _remove_stale(parent, final.name)
    tmp = parent / f"{STAGING_PREFIX}{final.name}.partial-{os.getpid()}"
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        (tmp / "figures").mkdir(parents=True)
    except OSError as exc:
        raise UserError(
            f"--out {final}: cannot write in {parent} ({exc.strerror or exc}); choose a folder "
            f"you can write to"
        ) from None
    try:
        yield tmp
        _publish(tmp, final)
    except OSError as exc:  # a full disk, a folder made read-only meanwhile: one line
        raise UserError(describe(final, exc)) from None
    except OutputError as exc:  # an atomic write inside: name the report's folder, not ours
        raise UserError(str(exc).replace(str(tmp), str(final))) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if not final.exists():
            remove_empty(made)


def _remove_stale(parent: Path, name: str) -> None:
    """Staging folders of earlier runs that were killed (their process is gone)."""
    for path in parent.glob(f"{STAGING_PREFIX}{name}.partial-*"):
        try:
            pid = int(path.name.rsplit("-", 1)[1])
            os.kill(pid, 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
        except (ValueError, OSError):  # not ours, or a live process of another user
            continue


def _publish(tmp: Path, final: Path) -> None:
    if final.is_dir() and not any(final.iterdir()):
        final.rmdir()
    if not final.exists():
        os.rename(tmp, final)
        return
    # --force into a folder with files: replace the report's own entries, keep the rest.
    for entry in sorted(tmp.iterdir()):
        target = final / entry.name
        if entry.is_dir() and target.is_dir():
            old = tmp / f"{STAGING_PREFIX}old-{entry.name}"
            os.rename(target, old)
        os.replace(entry, target)


def run_lab(
    data=None,
    out=None,
    *,
    force: bool = False,
    stream=None,
    plant=None,
    diagnosis: bool = True,
    fmt: str = "png",
    partial: bool = False,
    executor=None,
) -> Path:
    """Write the lab report; returns its folder.

    data: folder of experiment files (None: the built-in example recordings); out: the report
    folder (None: ./jaxcart-lab or a numbered one); force: overwrite an existing report;
    stream: where progress goes (default stderr); plant: a starting model (a
    :class:`jaxcart.Plant`, e.g. from a plant file): its B_eq, f_c and effects start the lab's
    model, and the parts refit B_eq and f_c from the recordings as usual; diagnosis: add the
    section that diagnoses each recording (most of the run time); fmt: the figures' format,
    "png", "svg" or "pdf" (report.html embeds PNG and SVG; with PDF it embeds a PNG copy);
    partial: a file that cannot be read costs only its part, said in the report and in
    results.json's ``data.broken`` (``jaxcart class``), instead of refusing the lab.
    executor: what makes the fits' exact runs several at a time (a
    :class:`jaxcart.workers.Helpers` the caller owns; default: one after the other here).
    """
    fmt = check_format(fmt)
    with jax.enable_x64(True):  # fits and exact checks need float64
        return _run_lab(
            data,
            out,
            force=force,
            stream=stream,
            plant=plant,
            diagnosis=diagnosis,
            fmt=fmt,
            partial=partial,
            executor=executor,
        )


def _run_lab(
    data,
    out,
    *,
    force,
    stream,
    plant=None,
    diagnosis=True,
    fmt="png",
    partial=False,
    executor=None,
) -> Path:
    started = time.perf_counter()
    folder = Path(data) if data is not None else builtin_dir()
    # Every input read and checked before anything is computed.
    inputs = find_inputs(folder, partial=partial)
    final = output_dir(out, force=force)
    with staged(final) as tmp:
        write_used(inputs, tmp, final)  # raw .mat data: the lab.toml and experiment files used
        lab = Lab(
            out=tmp, inputs=inputs, doc=Document(TITLE), stream=stream, started=started, fmt=fmt
        )
        _sections(lab, folder, data is None, plant, diagnosis, executor)
    lab.say(
        f"done: {final / 'report.md'}, {final / 'report.html'}, {final / 'results.json'} "
        f"({len(lab.figures)} figures) in {time.perf_counter() - started:.1f} s"
    )
    return final


@dataclass(frozen=True, eq=False)
class LabResults:
    """Every part's result (see each part's module); ``agreement``: the tap's and Part (ii)'s
    B_eq compared (None without both); ``diagnosis``: slot -> diagnosis, or None when the
    report leaves that section out."""

    prelab: prelab.Prelab
    part_i: part_i.TapResult
    part_ii: part_ii.P50Result
    agreement: part_ii.Agreement | None
    part_iii: part_iii.Part3
    part_iv: part_iv.PIResult
    part_v: part_v.PIDResult
    diagnosis: object = None
    cart: object = None
    designs: object = None


def compute(
    inputs,
    start: CartModel,
    *,
    diagnosis: bool = True,
    fit=fits.fit,
    say=lambda t: None,
    executor=None,
) -> LabResults:
    """Every part of the lab from the recordings ``inputs`` and the starting model, in the
    order their data need: the tap's model feeds Parts (ii) and (iii), Part (iii)'s f_c feeds
    Parts (iv) and (v), the pre-lab's tuned gains feed Part (v). ``fit``: the fitter every
    part uses (:func:`tuning.lab.fits.fit`). Another estimate of the cart (a joint fit over
    every recording, say) goes in as the ``model`` argument of the parts that simulate with
    it, and :func:`tuning.lab.part_ii.agreement` is the one place the tap's and the step's
    B_eq are compared. executor: the command's helper processes for the exact runs (the
    parts' fits and the diagnosis share them), else each run is made in this process.

    Two pieces run in threads beside the parts, each collected here before any result that
    holds it is built: the joint diagnosis (it needs only the recordings; while one compiles,
    the other fits) and the PID's design for the fitted cart (beside Part (v)); Part (v)'s
    designs are predicted on that cart once it has its design."""
    if executor is not None:
        fit = functools.partial(fit, executor=executor)
    recordings = inputs.recordings
    found = None
    if diagnosis:
        found = Background(diagnosis_section.compute, inputs, say, executor=executor)
    pre = prelab.compute(say=say)
    tap = part_i.compute(recordings.get("tap"), start, fit=fit, say=say)
    step = part_ii.compute(recordings.get("p_step"), tap.model, fit=fit, say=say)
    friction = part_iii.compute(recordings, tap.model, fit=fit, say=say)
    pi = part_iv.compute(recordings.get("pi"), friction.model, say=say)
    found = found.result() if found is not None else None
    # The cart once, from every recording (repeats too), in the diagnosis's structure; Part
    # (v) simulates the measured run on it (the gains re-tuned on it go to gains.json).
    tap_b = None if tap.fit is None else (tap.model.B_eq, tap.model.B_eq_stderr)
    known = {"B_eq": friction.model.B_eq, "f_c": friction.model.f_c}
    joint = cart.compute(inputs, tap_b, found, start=known, fit=fit, say=say)
    retune = None
    if joint is not None:
        say("the cart: the PID tuned for the cart as measured (robust over its uncertainty)")
        retune = Background(cart.retune, joint, executor=executor)
    model = cart.model_of(joint, friction.model)
    run = recordings.get("pid")
    # The recorded run on the cart with its own drive values, as the designs' section has it.
    own = part_v_design.own_cart(joint, run) if joint is not None and run is not None else None
    pid = part_v.compute(run, model, pre.gains, plant=own, say=say)
    joint = cart.with_retune(joint, retune.result() if retune is not None else None)
    designs = part_v_design.compute(
        recordings.get("pid"), joint, pre.gains, inputs.runs(), executor=executor, say=say
    )
    return LabResults(
        pre, tap, step, part_ii.agreement(step), friction, pi, pid, found, joint, designs
    )


def values(r: LabResults) -> list:
    """The summary's numbers, part by part."""
    return [
        *prelab.values(r.prelab),
        *part_i.values(r.part_i),
        *part_ii.values(r.part_ii),
        *part_iii.values(r.part_iii),
        *part_iv.values(r.part_iv),
        *part_v.values(r.part_v),
        *part_v_design.values(r.designs),
    ]


def _sections(lab: Lab, folder: Path, builtin: bool, plant, diagnosis: bool, executor) -> None:
    lab.diagnosis = diagnosis
    start = CartModel.starting(plant)
    if plant is not None:
        lab.say(f"starting model: {describe_plant(plant)}")
    lab.say(f"data: {'built-in example recordings' if builtin else folder}")
    for line in lab.inputs.summary_lines():
        lab.say("  " + line)
    r = compute(lab.inputs, start, diagnosis=diagnosis, say=lab.say, executor=executor)
    _introduction(lab, folder, builtin)
    render(lab, r)
    _summary(lab, values(r))
    elapsed = time.perf_counter() - lab.started
    lab.results["elapsed_seconds"] = elapsed
    lab.doc.paragraph(f"Report written by `jaxcart lab` in {elapsed:.0f} s.")
    _write(lab)


def render(lab: Lab, r: LabResults) -> None:
    """Every part's section of the report and its entry in results.json, in the handout's
    order; the tuned gains go to gains.json."""
    prelab.render(lab, r.prelab)
    part_i.render(lab, r.part_i)
    part_ii.render(lab, r.part_ii, r.agreement)
    part_iii_render.render(lab, r.part_iii)
    part_iv.render(lab, r.part_iv)
    part_v_render.render(lab, r.part_v, r.designs)
    lab.results.update(
        {
            "prelab": prelab.to_json(r.prelab),
            "part_i": part_i.to_json(r.part_i),
            "part_ii": part_ii.to_json(r.part_ii, r.agreement, diagnosis=lab.diagnosis),
            "part_iii": part_iii.to_json(r.part_iii),
            "part_iv": part_iv.to_json(r.part_iv),
            "part_v": {
                **part_v.to_json(r.part_v),
                "designs": part_v_design.to_json(r.designs),
            },
        }
    )
    if r.diagnosis is not None:
        diagnosis_section.render(lab, r.diagnosis, r.agreement)
        lab.results["diagnosis"] = diagnosis_section.to_json(r.diagnosis)
    cart.render(lab, r.cart)
    lab.results["cart"] = cart.to_json(r.cart)
    lab.gains = r.prelab.gains
    lab.gains_metrics = lab.results["prelab"]["pid"]["metrics"]
    if r.cart is not None:  # the gains to run on this cart: the likelier to meet the spec
        _gains_to_run(lab, r)


# ---------------------------------------------------------------- sections


def _introduction(lab: Lab, folder: Path, builtin: bool) -> None:
    doc, inputs = lab.doc, lab.inputs
    doc.paragraph(
        "Every number and figure the handout asks for, computed by `jaxcart lab`: the pre-lab "
        "(appendix constants, the PI stability bound from Routh and the root locus, a tuned "
        "PID design) and Parts (i) to (v) of the lab, each recording compared with "
        "simulations of the 1 ms digital loop (exact simulator: hard voltage clip, event-exact "
        "Coulomb stick-slip)."
    )
    doc.heading("Data")
    where = "the built-in example recordings" if builtin else f"`{folder}`"
    doc.paragraph(f"Recordings from {where}. Which file went to which part:")
    doc.bullets(inputs.summary_lines())
    synthetic = inputs.synthetic
    if synthetic is not None:
        doc.note(
            "These recordings are **synthetic**: generated once by jaxcart's exact simulator "
            '(event-exact stick-slip, hard clip) from the "true" cart below, which differs '
            "from the handout's model; positions are whole encoder counts. The fits below "
            "should recover these values."
        )
        rows = []
        names = {
            "M": ("cart mass M", "kg"),
            "B_eq": ("viscous friction B_eq", "kg/s"),
            "f_c": ("Coulomb friction f_c", "N"),
            "v_sat": ("amplifier saturation", "V"),
            ENCODER_PARAM: ("encoder resolution", "m/count"),
            "pid_kp": ("Part (v) recording's kp (the pre-lab's tuned PID)", "V/m"),
            "pid_kd": ("Part (v) recording's kd", "V s/m"),
            "pid_ki": ("Part (v) recording's ki", "V/(m s)"),
            "seed": ("random seed (encoder phase)", ""),
        }
        for key, (label, unit) in names.items():
            if key in synthetic:
                rows.append([label, f"{synthetic[key]:g}", unit])
        doc.table(["true parameter", "value", "unit"], rows, numeric=[False, True, False])
    doubts = [
        f"{Path(rec.path).name}: {w}"
        for rec in inputs.recordings.values()
        for w in getattr(rec, "warnings", ())
    ]
    if doubts:
        doc.note("What looks physically doubtful in the recordings: " + "; ".join(doubts) + ".")
    if inputs.broken:
        doc.note(
            "Files that cannot be used (each costs only its part): "
            + "; ".join(f"{name}: {why}" for name, _, why in inputs.broken)
            + ". Fix them and run the lab again."
        )
    missing = inputs.missing()
    if missing:
        parts_missing = sorted(
            {SLOTS[s][0] for s in missing}, key=["i", "ii", "iii", "iv", "v"].index
        )
        doc.note(
            "No recording for: "
            + "; ".join(f"Part ({SLOTS[s][0]}) {SLOTS[s][1]}" for s in missing)
            + ". Those items show simulations only (Parts "
            + ", ".join(f"({p})" for p in parts_missing)
            + ")."
        )
    lab.results["data"] = {
        "folder": str(folder),
        "builtin": builtin,
        "synthetic": synthetic,
        "recordings": {
            slot: (str(Path(r.path).name) if r is not None else None)
            for slot, r in ((s, inputs.recordings.get(s)) for s in SLOTS)
        },
        "how": dict(inputs.how),
        "missing": missing,
        "unused": [{"file": n, "reason": r} for n, r in inputs.unused],
        "broken": [{"file": n, "slot": s, "reason": r} for n, s, r in inputs.broken],
        "warnings": doubts,
    }


def _summary(lab: Lab, numbers: list) -> None:
    doc = lab.doc
    doc.heading("Summary")
    synthetic = lab.inputs.synthetic
    header = ["part", "quantity", "value", "unit"]
    if synthetic is not None:
        header += ["true value", "relative error"]
    rows = [_summary_row(v, synthetic) for v in numbers]
    doc.table(header, rows, numeric=[False, False, True, False] + [True, True][: len(header) - 4])
    doc.paragraph(
        "Every number is also in `results.json` (SI units; `results.mat` holds the same as a "
        "MATLAB struct `results`); the gains to run are in `gains.json` (the "
        f"{lab.gains_source.removeprefix('jaxcart lab: ')}; jaxcart gains-file format, every "
        "PID setting)."
    )
    lab.results["values"] = {v.key: v.to_json(synthetic) for v in numbers}


def _summary_row(v, synthetic) -> list:
    value, unit = v.value, v.unit
    shown_unit = unit
    if unit == "m" and value is not None:
        value, shown_unit = value * 1e3, "mm"
    shown = fmt(value)
    if value is not None and math.isinf(value) and unit == "s":
        shown, shown_unit = "does not settle within the horizon", ""
    row = [v.part, v.label, shown, shown_unit]
    if synthetic is None:
        return row
    true = v.true(synthetic)
    if true is None:
        return row + ["", ""]
    err = relative_error(v.value, true)
    return row + [
        fmt(true * (1e3 if unit == "m" else 1.0)),
        "n/a" if err is None else f"{100 * err:.2g} %",
    ]


def _gains_to_run(lab: Lab, r) -> None:
    """gains.json's design where the lab has a cart as measured: the one tuned for it, unless
    the pre-lab's is likelier to meet the spec by more than one drawn cart's share (P(spec):
    both predicted on the same carts, with the same model error,
    :mod:`tuning.lab.part_v_design`); its prediction and margins go with it."""
    retuned, prelab = r.designs.get("retuned"), r.designs.get("prelab")
    p_new, p_old = retuned.prediction.p_meet, prelab.prediction.p_meet
    # Likelier by more than one drawn cart's share: less is what the carts do not resolve
    # (on the built-in cart both are 1 - 6e-8, the tuned one 1e-9 behind).
    if p_old > p_new + 1.0 / prelab.prediction.n:
        lab.gains = prelab.controller  # (gains_metrics: the pre-lab's, set above)
        lab.gains_source = (
            f"jaxcart lab: pre-lab design (handout model), which meets the spec with a chance "
            f"of {p_old:.0%} against {p_new:.0%} for the one tuned for it"
        )
        lab.gains_extra = {
            "prediction": prelab.prediction.to_json(),
            "margins": prelab.margins.to_json(),
        }
        return
    lab.gains, lab.gains_metrics = r.cart.tuned.gains, r.cart.tuned.exact.as_dict()
    lab.gains_source = "jaxcart lab: PID tuned for the cart as measured (the recordings)"
    lab.gains_extra = {
        "prediction": retuned.prediction.to_json(),
        "margins": r.cart.design.margins.to_json(),
        "binding": r.cart.design.binding,
    }


# ---------------------------------------------------------------- writing


def _write(lab: Lab) -> None:
    out = lab.out
    write_json(out / "results.json", lab.results, force=True)
    write_mat_report(out / "results.mat", to_jsonable(lab.results), name="results", force=True)
    (out / "report.md").write_text(lab.doc.to_markdown())
    (out / "report.html").write_text(lab.doc.to_html(out))
    if lab.gains is not None:
        write_gains(
            out / "gains.json",
            lab.gains,
            force=True,
            source=lab.gains_source,
            metrics=lab.gains_metrics,
            **lab.gains_extra,
        )
