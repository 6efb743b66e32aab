"""Step metrics of a run, against the spec (numpy only; the conventions of jaxcart.metrics).

For a step of size A = r_final - y_0 (each set point of a slider run is one step):
    rise_time:          first time y reaches 90 % of the step minus first time it reaches 10 % [s]
    settling_time:      time of the first sample after the last one with |y - r| > 2 % of |A|
                        (inf: the run ends outside the band) [s]
    overshoot:          max(0, (max y - r) / A) * 100 [%], in the direction of the step
    steady_state_error: |r - y| at the last sample [m]
    peak_voltage:       max |u| [V]

The spec is the gains file's own (``jaxcart tune`` writes it), else the lab's: settling within
1 s in the 2 % band, overshoot under 5 %.
"""

from __future__ import annotations

import math

import numpy as np

SETTLING_BAND = 0.02
#: The lab's specification when the gains file carries none.
LAB_SPEC = {"settling_time": 1.0, "overshoot": 5.0}
METRICS = ("rise_time", "settling_time", "overshoot", "steady_state_error", "peak_voltage")
UNITS = {
    "rise_time": "s",
    "settling_time": "s",
    "overshoot": "%",
    "steady_state_error": "mm",
    "peak_voltage": "V",
}


def step_metrics(time, position, reference, command, band: float = SETTLING_BAND) -> dict:
    """The metrics of one step (arrays over the step, reference constant after its start)."""
    t = np.asarray(time, dtype=float)
    y = np.asarray(position, dtype=float)
    r_final = float(np.asarray(reference, dtype=float)[-1])
    amplitude = r_final - y[0]
    if amplitude == 0 or t.size < 2:
        return {}
    z = (y - y[0]) / amplitude
    t10 = t[np.argmax(z >= 0.1)] if np.any(z >= 0.1) else math.inf
    t90 = t[np.argmax(z >= 0.9)] if np.any(z >= 0.9) else math.inf
    outside = np.nonzero(np.abs(y - r_final) > band * abs(amplitude))[0]
    if outside.size == 0:
        settling = 0.0
    elif outside[-1] + 1 >= t.size:
        settling = math.inf
    else:
        settling = float(t[outside[-1] + 1] - t[0])
    return {
        "rise_time": float(t90 - t10) if math.isfinite(t10 + t90) else math.inf,
        "settling_time": settling,
        "overshoot": max(0.0, float(z.max() - 1.0) * 100.0),
        "steady_state_error": abs(r_final - float(y[-1])),
        "peak_voltage": float(np.abs(np.asarray(command, dtype=float)).max()),
    }


def segments(reference) -> list[tuple[int, int]]:
    """[start, stop) of each stretch of constant reference (a step run: one)."""
    r = np.asarray(reference, dtype=float)
    if r.size == 0:
        return []
    edges = [0] + [int(i) + 1 for i in np.nonzero(np.diff(r))[0]] + [r.size]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b - a >= 2]


def run_metrics(result) -> list[dict]:
    """The metrics of each set point of a run (a :class:`hw.loop.RunResult`)."""
    out = []
    for a, b in segments(result.reference):
        m = step_metrics(
            result.time[a:b] - result.time[a],
            result.position[a:b],
            result.reference[a:b],
            result.command[a:b],
        )
        if m:
            out.append({"set_point": float(result.reference[a]), **m})
    return out


def spec_problem(spec) -> tuple[str, str] | None:
    """(field, what is wrong) of a gains file's spec that :func:`spec_of` would pass over
    (settling 0, overshoot -1, a string), or None."""
    if not isinstance(spec, dict):
        return "spec", "expected an object with settling_time [s] and overshoot [%]"
    for key in LAB_SPEC:
        value = spec.get(key)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            return f"spec.{key}", f"{value!r}: give a positive number ({UNITS[key]})"
    return None


def spec_of(meta: dict) -> dict:
    """The spec of a gains file's metadata (settling_time [s], overshoot [%]), else the lab's."""
    spec = meta.get("spec") if isinstance(meta, dict) else None
    out = dict(LAB_SPEC)
    if isinstance(spec, dict):
        for key in LAB_SPEC:
            value = spec.get(key)
            if isinstance(value, int | float) and not isinstance(value, bool) and value > 0:
                out[key] = float(value)
    return out


def _fmt(name: str, value: float) -> str:
    if not math.isfinite(value):
        return "never" if name in ("settling_time", "rise_time") else "inf"
    if name == "steady_state_error":
        value *= 1e3
    return f"{value:.3g} {UNITS[name]}"


def comparison_lines(run: list[dict], sim: list[dict] | None, spec: dict) -> list[str]:
    """Lines: each metric of the run, the simulation of the same gains and the spec."""
    lines = []
    for i, m in enumerate(run):
        s = sim[i] if sim and i < len(sim) else {}
        lines.append(f"set point {m['set_point']:g} m:")
        for name in METRICS:
            bound = spec.get(name)
            verdict = ""
            if bound is not None:
                verdict = "  meets" if m[name] < bound else "  FAILS"
                verdict += f" the spec (< {_fmt(name, bound)})"
            simulated = f"  simulated {_fmt(name, s[name])}" if name in s else ""
            lines.append(f"  {name:20s} {_fmt(name, m[name]):>10s}{simulated}{verdict}")
    return lines
