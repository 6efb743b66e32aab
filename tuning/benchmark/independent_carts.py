"""Proven on carts the tool did not build: the whole lab, end to end, on carts of the independent
generator (:mod:`tuning.verification`), and the gains it hands back run on the true cart.

For each cart of :data:`CARTS` (the lab's friction, plus one thing the handout's model leaves
out: a 12 ms amplifier lag, a drive limit that differs from run to run, a current-limited
amplifier, stiction, an extra 0.5 kg, a cable spring, a dead band):

1. the handout's recordings are made on it with what real recordings carry
   (:data:`tuning.verification.REALISTIC`: the encoder read by the controller, jitter, drift,
   a 0.1 ms lag, the drive drawn anew for each run): the tap, P 50, the 0.1 V/s ramp, P 10, PI
   and the pre-lab's PID (the pre-lab's design on the handout's model, as ``jaxcart lab``
   tunes it), the specs of :data:`tuning.lab.data.SPECS`;
2. ``jaxcart lab --data`` runs on them (:func:`tuning.lab.report.run_lab`, with the caller's
   helpers), and hands back ``gains.json``: the PID tuned for the cart as measured, with its
   prediction (the settling time on the fitted cart and its 90 % band: the fit's, widened by
   how far the fitted cart misses the recorded steps, the "miss" column);
3. those gains run on the true cart (:func:`tuning.verification.run_controller`, the same
   artefacts with the cart's own drive, no run-to-run draw): does the run meet the spec, does
   its settling time lie inside the predicted band, how far is it from the predicted one.

    python -m tuning.benchmark.independent_carts [--only NAME,...] [--out DIR] [--json OUT]
        [--no-diagnosis]

Prints one row per cart and the summary the issue judges by (every true cart meets the spec,
every true settling time inside its band, the median error of the predicted settling time).
A cart takes its recordings' 30 s and the lab's time: with the joint diagnosis (the default,
as ``jaxcart lab`` runs) up to twenty minutes on a busy 2-core machine; ``--no-diagnosis``
(``jaxcart lab --no-diagnosis``: the cart fitted in the lab's own structure, B_eq, f_c and
v_sat, the model's miss of the recorded steps widening the band) a few minutes.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax

from hw.control_law import PID
from hw.gains import read_gains
from jaxcart import xlaflags
from jaxcart.cache import enable_persistent_cache
from jaxcart.parallel import use_cpu_devices
from jaxcart.workers import Helpers
from tuning.design.tune import tune
from tuning.lab import data
from tuning.lab.report import run_lab
from tuning.verification import REALISTIC, TrueCart, make_recording, run_controller
from tuning.verification import experiments as ex

#: What every cart has: a lab cart's friction and its amplifier limit just under the software's.
BASE = {"B_eq": 2.5, "f_c": 0.4, "v_sat": 5.8}
#: The carts: {name: (what differs from BASE, what differs from REALISTIC artefacts)}.
CARTS = {
    "friction": ({}, {}),
    "lag 12 ms": ({"lag": 0.012}, {}),
    "drive limit per run": ({"v_sat": 5.3}, {"limit_spread": 0.06}),
    "current limit 1.2 A": ({"i_max": 1.2}, {}),
    "stiction 0.8 N": ({"f_s": 0.8, "v_stribeck": 0.002}, {}),
    "extra 0.5 kg": ({"M": 1.44}, {}),
    "cable spring 4 N/m": ({"k_s": 4.0, "y_rest": 0.0}, {}),
    "dead band 0.3 V": (dict(deadzone=0.3), {}),  # (TrueCart's field, by keyword)
}
#: The tap's push (speed [m/s]) and rest before it [s].
TAP = {"speed": 1.0, "rest": 0.5}
#: The true run's artefacts: the recordings', with the cart's own drive (no run-to-run draw).
TRUE_RUN = {"gain_spread": 0.0, "limit_spread": 0.0}
#: The issue's bound on the median error of the predicted settling time [s].
MEDIAN_ERROR = 0.030


def experiments(prelab) -> dict:
    """{file stem: the independent generator's experiment} of the handout's recordings (the
    specs of :data:`tuning.lab.data.SPECS`; Part (v)'s PID is ``prelab``)."""
    out = {}
    for spec in data.SPECS:
        if spec.kind == "tap":
            out[spec.stem] = ex.tap(horizon=spec.horizon, **TAP)
        elif spec.kind == "open_loop":
            out[spec.stem] = ex.voltage_ramp(spec.ramp, horizon=spec.horizon)
        else:
            pid = prelab if spec.slot == "pid" else PID(**spec.controller)
            out[spec.stem] = ex.step(pid, spec.step, horizon=spec.horizon)
    return out


def write_cart(folder: Path, truth: dict, artefacts: dict, prelab, *, seed: int = 0) -> TrueCart:
    """The handout's recordings of the cart ``truth`` ({name: value} of
    :class:`tuning.verification.TrueCart`) in ``folder``, and its lab.toml; the true cart."""
    folder.mkdir(parents=True, exist_ok=True)
    cart = TrueCart.from_values(truth)
    made = REALISTIC.replace(**artefacts)
    for k, (stem, experiment) in enumerate(experiments(prelab).items()):
        make_recording(cart, experiment, folder / f"{stem}.toml", made, seed=seed * 100 + k)
    lines = ["[recordings]"] + [f'{s.slot} = "{s.stem}.toml"' for s in data.SPECS]
    (folder / "lab.toml").write_text("\n".join(lines) + "\n")
    return cart


def judge(name: str, cart: TrueCart, report: Path, artefacts: dict, prelab, seed: int) -> dict:
    """One cart's row: the handed-back gains and their prediction (the report's), their run on
    the true cart, and the pre-lab's gains on it for comparison."""
    gains_file = report / "gains.json"
    meta = json.loads(gains_file.read_text())
    prediction = meta["prediction"]
    settling = prediction["metrics"]["settling_time"]
    lo, hi = (float(x) for x in settling["band"])
    true_artefacts = REALISTIC.replace(**{**artefacts, **TRUE_RUN})
    true = run_controller(cart, read_gains(gains_file), artefacts=true_artefacts, seed=seed).metrics
    handout = run_controller(cart, prelab, artefacts=true_artefacts, seed=seed).metrics
    nominal = float(settling["nominal"])
    return {
        "cart": name,
        "gains": {k: meta["controller"][k] for k in ("kp", "ki", "kd")},
        "binding": meta.get("binding", ""),
        "p_meet": prediction["p_meet"],
        "predicted_settling": nominal,
        "band": [lo, hi],
        "band_fit": [float(x) for x in settling.get("band_fit", settling["band"])],
        "model_error": float(settling.get("model_error", 0.0)),
        "true_settling": true.settling_time,
        "true_overshoot": true.overshoot,
        "meets": true.meets(),
        "inside": bool(lo <= true.settling_time <= hi),
        "error": nominal - true.settling_time,
        "prelab_settling": handout.settling_time,
        "prelab_overshoot": handout.overshoot,
        "prelab_meets": handout.meets(),
    }


def measure(
    names=tuple(CARTS),
    *,
    out: Path,
    helpers=None,
    diagnosis: bool = True,
    say=lambda t: None,
    each=lambda r: None,
) -> dict:
    """Every cart of ``names``: recordings in ``out/NAME/data``, the lab's report in
    ``out/NAME/report`` (``diagnosis``: with its joint diagnosis); {"rows": [...], "summary":
    {...}, "prelab": gains, "diagnosis": bool}. ``each(result)`` is called after every cart
    with the result so far (a long run keeps what it has)."""
    with jax.enable_x64(True):
        prelab = tune(progress=False).gains  # the pre-lab's design, as the lab tunes it
    rows = []
    for name in names:
        # A cart's seed is its place in CARTS: its recordings do not depend on which carts run.
        seed = list(CARTS).index(name)
        changes, artefacts = CARTS[name]
        slug = "".join(ch if ch.isalnum() else "_" for ch in name)
        t0 = time.perf_counter()
        say(f"{name}: the handout's recordings on the independent generator")
        cart = write_cart(out / slug / "data", {**BASE, **changes}, artefacts, prelab, seed=seed)
        say(f"{name}: jaxcart lab --data")
        with open(out / slug / "lab.log", "w") as log:
            report = run_lab(
                out / slug / "data", out / slug / "report", force=True, stream=log,
                executor=helpers, diagnosis=diagnosis,
            )  # fmt: skip
        row = judge(name, cart, report, artefacts, prelab, seed)
        row["seconds"] = time.perf_counter() - t0
        say(f"{name}: {_row_text(row)}")
        rows.append(row)
        each(_result(rows, prelab, diagnosis))
    return _result(rows, prelab, diagnosis)


def _result(rows, prelab, diagnosis) -> dict:
    return {
        "rows": rows, "summary": summary(rows), "prelab": prelab.to_dict(), "diagnosis": diagnosis
    }  # fmt: skip


def summary(rows) -> dict:
    """What the issue judges by, over the rows."""
    errors = [abs(r["error"]) for r in rows]
    return {
        "carts": len(rows),
        "all_meet": all(r["meets"] for r in rows),
        "all_inside": all(r["inside"] for r in rows),
        "median_error": statistics.median(errors) if errors else None,
        "median_error_under": MEDIAN_ERROR,
        "prelab_meets": sum(r["prelab_meets"] for r in rows),
    }


def _row_text(r) -> str:
    lo, hi = r["band"]
    return (
        f"predicted {r['predicted_settling']:.3f} s [{lo:.3f}, {hi:.3f}], true "
        f"{r['true_settling']:.3f} s ({'inside' if r['inside'] else 'OUTSIDE'}), overshoot "
        f"{r['true_overshoot']:.2f} %, {'meets' if r['meets'] else 'FAILS'} the spec"
    )


def table(result: dict) -> str:
    """The rows and the summary, as text."""
    head = (
        f"{'cart':<22}{'kp':>7}{'ki':>7}{'kd':>7}{'P(spec)':>8}{'predicted [s]':>14}"
        f"{'90 % band [s]':>16}{'miss [ms]':>10}{'true [s]':>9}{'in':>4}{'error [ms]':>11}"
        f"{'OS [%]':>7}"
        f"{'meets':>6}{'pre-lab [s]':>12}"
    )
    lines = [head]
    for r in result["rows"]:
        g = r["gains"]
        lo, hi = r["band"]
        pre = f"{r['prelab_settling']:.3f}" + ("" if r["prelab_meets"] else "*")
        lines.append(
            f"{r['cart']:<22}{g['kp']:7.1f}{g['ki']:7.2f}{g['kd']:7.2f}{r['p_meet']:8.0%}"
            f"{r['predicted_settling']:14.3f}{f'{lo:.3f}-{hi:.3f}':>16}"
            f"{r['model_error'] * 1e3:10.1f}{r['true_settling']:9.3f}"
            f"{'yes' if r['inside'] else 'NO':>4}{r['error'] * 1e3:11.1f}"
            f"{r['true_overshoot']:7.2f}{'yes' if r['meets'] else 'NO':>6}{pre:>12}"
        )
    s = result["summary"]
    lines += [
        "",
        f"true carts meeting the spec with the handed-back gains: "
        f"{sum(r['meets'] for r in result['rows'])} of {s['carts']}; "
        f"true settling inside the predicted band: "
        f"{sum(r['inside'] for r in result['rows'])} of {s['carts']}; "
        f"median |error| of the predicted settling {s['median_error'] * 1e3:.1f} ms "
        f"(issue: under {MEDIAN_ERROR * 1e3:g} ms)",
        f"the pre-lab's gains (handout's model) meet the spec on {s['prelab_meets']} of "
        f"{s['carts']} true carts (* where they do not); the lab "
        + ("with its joint diagnosis" if result.get("diagnosis", True) else "without diagnosis"),
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tuning.benchmark.independent_carts",
        description="The lab end to end on carts of the independent generator: recordings "
        "in, gains out, run on the true cart.",
    )
    parser.add_argument("--only", default=",".join(CARTS), help="carts, comma-separated")
    parser.add_argument("--out", metavar="DIR", help="keep recordings and reports here")
    parser.add_argument("--json", metavar="OUT", help="also write the result as JSON")
    parser.add_argument("--helpers", type=int, default=None, help="helper processes")
    parser.add_argument(
        "--no-diagnosis", action="store_true",
        help="the lab without its joint diagnosis (jaxcart lab --no-diagnosis): minutes a cart",
    )  # fmt: skip
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.only.split(",") if n.strip()]
    unknown = [n for n in names if n not in CARTS]
    if unknown or not names:
        parser.error(f"--only: some of {', '.join(CARTS)}")
    # As the command line does, before jax starts: loops as kernels, the compilation cache,
    # one XLA device per core.
    xlaflags.request()
    enable_persistent_cache()
    use_cpu_devices()
    with tempfile.TemporaryDirectory(prefix="jaxcart-carts-") as tmp, Helpers(args.helpers) as h:
        out = Path(args.out) if args.out else Path(tmp)
        result = measure(
            names, out=out, helpers=h, diagnosis=not args.no_diagnosis,
            say=lambda t: print(t, file=sys.stderr),
            each=lambda r: args.json and _write(args.json, r),
        )  # fmt: skip
    print(table(result))
    return 0


def _write(path, result) -> None:
    Path(path).write_text(json.dumps(result, indent=2, default=str))


if __name__ == "__main__":
    sys.exit(main())
