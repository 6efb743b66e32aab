"""The concealed-effect suite: recordings made by the exact simulator through the encoder, each
effect plain and concealed (brief, masked by integral action, without a column v, combined
with a second effect), clean recordings and parameter errors; and its score table.

    python -m tuning.estimation.diagnose.suite [--fast] [--only NAME,...]   (or: jaxcart diagnose
    --suite)

Every case is written as an experiment file (TOML + CSV) in a temporary folder and read back,
so the diagnosis sees exactly what a user's file gives it (a case "without v" has its column v
dropped).
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Case:
    name: str
    group: str  # "clean" | "parameter" | "plain" | "concealed"
    truth: dict  # plant values of the truth (SI)
    kind: str = "step"  # "step" | "ramp" | "open_ramp" | "tap"
    amplitude: float = 0.3
    kp: float = 40.0
    ki: float = 0.0
    kd: float = 3.0
    v_limit: float = 6.0
    drop_v: bool = False
    expect: tuple = ()  # effects that should be named
    corrected: bool = False  # a parameter error: corrected parameters, nothing left out
    seed: int = 1


B = {"B_eq": 4.6}
CASES = (
    Case("clean PD step", "clean", B),
    Case("clean PID step", "clean", B, ki=5.0),
    Case("clean ramp reference", "clean", B, kind="ramp", amplitude=0.2),
    Case("clean tap", "clean", {"B_eq": 1.5}, kind="tap"),
    Case("heavier cart (M)", "parameter", {**B, "M": 1.25}, corrected=True),
    Case("weaker motor (gamma)", "parameter", {**B, "gamma_scale": 0.8}, corrected=True),
    Case("saturation plain", "plain", {**B, "v_sat": 4.0}, amplitude=0.4, expect=("saturation",)),
    Case(
        "saturation brief (first 0.1 s)",
        "concealed",
        {**B, "v_sat": 5.0},
        amplitude=0.2,
        kp=30.0,
        expect=("saturation",),
    ),
    Case("coulomb plain", "plain", {**B, "f_c": 0.4}, expect=("coulomb",)),
    Case(
        "coulomb under PI (error goes to 0)",
        "concealed",
        {**B, "f_c": 0.3},
        ki=20.0,
        expect=("coulomb",),
    ),
    Case("coulomb without v", "concealed", {**B, "f_c": 0.4}, drop_v=True, expect=("coulomb",)),
    Case("coulomb on a tap", "plain", {"B_eq": 1.5, "f_c": 0.44}, kind="tap", expect=("coulomb",)),
    Case(
        "stiction plain (small step, stick-slip)",
        "plain",
        {**B, "f_c": 0.3, "f_s": 0.6},
        amplitude=0.03,
        kp=15.0,
        ki=30.0,
        kd=1.0,
        expect=("coulomb", "stiction"),
    ),
    Case(
        "stiction under PI",
        "concealed",
        {**B, "f_c": 0.3, "f_s": 0.5},
        amplitude=0.02,
        kp=20.0,
        ki=40.0,
        kd=1.0,
        expect=("coulomb", "stiction"),
    ),
    Case("delay plain", "plain", {**B, "delay": 0.004}, kp=60.0, kd=4.0, expect=("delay",)),
    Case(
        "delay without v",
        "concealed",
        {**B, "delay": 0.002},
        kp=60.0,
        kd=4.0,
        drop_v=True,
        expect=("delay",),
    ),
    Case(
        "delay with coulomb",
        "concealed",
        {**B, "delay": 0.003, "f_c": 0.3},
        kp=60.0,
        kd=4.0,
        expect=("coulomb", "delay"),
    ),
    Case("deadzone plain", "plain", {**B, "deadzone": 0.4}, expect=("deadzone",)),
    Case(
        "deadzone without v", "concealed", {**B, "deadzone": 0.3}, drop_v=True, expect=("deadzone",)
    ),
    Case(
        "deadzone on an open-loop ramp (= coulomb)",
        "concealed",
        {**B, "deadzone": 0.5},
        kind="open_ramp",
        expect=("deadzone",),
    ),
    Case("spring plain", "plain", {**B, "k_s": 6.0, "y_rest": 0.0}, expect=("spring",)),
    Case(
        "spring under PID",
        "concealed",
        {**B, "k_s": 3.0, "y_rest": 0.0},
        ki=10.0,
        expect=("spring",),
    ),
    Case(
        "current limit plain",
        "plain",
        {**B, "i_max": 1.5},
        amplitude=0.4,
        expect=("current_limit",),
    ),
    Case(
        "current limit with coulomb",
        "concealed",
        {**B, "i_max": 2.0, "f_c": 0.3},
        amplitude=0.4,
        expect=("coulomb", "current_limit"),
    ),
    Case(
        "saturation with coulomb",
        "concealed",
        {**B, "v_sat": 4.5, "f_c": 0.3},
        amplitude=0.3,
        expect=("coulomb", "saturation"),
    ),
)
FAST = ("clean PD step", "heavier cart (M)", "coulomb plain", "saturation brief (first 0.1 s)")


def make_case(case: Case, folder) -> Path:
    """Simulate ``case`` exactly, through the encoder, and write it as an experiment file."""
    import jaxcart as jc
    from jaxcart.plantspec import build_plant
    from jaxcart.synthetic import make_recording, make_tap_recording, write_recording

    slug = "".join(ch if ch.isalnum() else "_" for ch in case.name).strip("_")
    path = Path(folder) / f"{slug}.toml"
    if case.kind == "tap":
        truth = build_plant(case.truth, motor_connected=False)
        rec = make_tap_recording(truth, speed=0.6, rest=0.3, horizon=1.5, seed=case.seed)
    else:
        truth = build_plant(case.truth)
        pid = jc.PID(kp=case.kp, ki=case.ki, kd=case.kd, v_limit=case.v_limit)
        if case.kind == "step":
            exp = jc.step(case.amplitude, horizon=2.0)
        elif case.kind == "ramp":
            exp = jc.ramp(case.amplitude, horizon=2.0)
        else:
            exp = jc.voltage_ramp(0.5, horizon=3.0)
            pid = None
        rec = make_recording(truth, pid, exp, seed=case.seed)
    write_recording(rec, path, force=True)
    if rec.kind == "tap":
        text = path.read_text()
        if "[tap]" not in text:
            path.write_text(text + "\n[tap]\nmotor_connected = false\n")
    if case.drop_v:
        _drop_column(path.with_suffix(".csv"), "v")
    return path


def _drop_column(csv_path: Path, column: str) -> None:
    with csv_path.open() as f:
        rows = list(csv.reader(f))
    header = rows[0]
    if column not in header:
        return
    k = header.index(column)
    with csv_path.open("w", newline="") as f:
        w = csv.writer(f)
        for row in rows:
            w.writerow(row[:k] + row[k + 1 :])


def judge(case: Case, d) -> dict:
    named = set(d.left_out)
    alternatives = [set(e) for e in d.equivalent]
    expect = set(case.expect)
    if case.corrected:
        correct = not named and bool(d.corrected_parameters)
    elif not expect:
        correct = not named
    else:
        correct = named == expect or expect in alternatives
    false_alarm = case.group in ("clean", "parameter") and bool(named)
    return {
        "case": case.name,
        "group": case.group,
        "expected": sorted(expect) or (["corrected M/gamma"] if case.corrected else []),
        "named": sorted(named),
        "corrected": d.corrected_parameters,
        "equivalent": d.equivalent,
        "correct": correct,
        "false_alarm": false_alarm,
        "rms_before": d.rms_before,
        "rms_after": d.rms_after,
        "ratio": d.rms_before / d.rms_after if d.rms_after > 0 else math.inf,
        "seconds": d.seconds,
    }


def run_suite(names=None, progress=False, out=sys.stdout) -> list[dict]:
    from jaxcart.files import read_experiment
    from tuning.estimation.diagnose import diagnose

    chosen = [c for c in CASES if names is None or c.name in names]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in chosen:
            path = make_case(case, tmp)
            t = time.perf_counter()
            d = diagnose([read_experiment(path)], progress=progress)
            row = judge(case, d)
            row["seconds"] = round(time.perf_counter() - t, 2)
            rows.append(row)
            print(_row_text(row), file=out, flush=True)
    return rows


def _row_text(r) -> str:
    named = ", ".join(r["named"]) or (
        "corrected " + ", ".join(r["corrected"]) if r["corrected"] else "-"
    )
    if r["equivalent"]:
        named += " (or " + "; ".join("+".join(e) for e in r["equivalent"]) + ")"
    return (
        f"{'ok  ' if r['correct'] else 'MISS'} {r['case']:<42} {r['group']:<9} named: {named:<40} "
        f"RMS {r['rms_before'] * 1e3:8.4f} -> {r['rms_after'] * 1e3:7.4f} mm "
        f"({r['ratio']:7.1f}x) {r['seconds']:5.1f} s"
    )


def summary(rows) -> str:
    n = len(rows)
    correct = sum(r["correct"] for r in rows)
    guard = [r for r in rows if r["group"] in ("clean", "parameter")]
    alarms = sum(r["false_alarm"] for r in rows)
    ratios = [r["ratio"] for r in rows]
    effect_ratios = [r["ratio"] for r in rows if r["group"] in ("plain", "concealed", "parameter")]
    secs = [r["seconds"] for r in rows]
    return (
        f"correct names: {correct}/{n}; false alarms on clean and parameter-error cases: "
        f"{alarms}/{len(guard)}; median RMS ratio before/after: {statistics.median(ratios):.1f}x "
        f"(all), {statistics.median(effect_ratios) if effect_ratios else float('nan'):.1f}x "
        f"(cases with an effect or parameter error); seconds per recording: median "
        f"{statistics.median(secs):.1f}, max {max(secs):.1f}"
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m tuning.estimation.diagnose.suite")
    p.add_argument("--fast", action="store_true", help="the CI subset")
    p.add_argument("--only", help="comma-separated case names")
    p.add_argument("--progress", action="store_true")
    args = p.parse_args(argv)
    names = FAST if args.fast else (args.only.split(",") if args.only else None)
    rows = run_suite(names, progress=args.progress)
    print(summary(rows))
    return 0


if __name__ == "__main__":
    from jaxcart.parallel import use_cpu_devices

    use_cpu_devices()
    sys.exit(main())
