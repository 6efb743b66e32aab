"""Part (v) of the report drawn from its result (:class:`tuning.lab.part_v.PIDResult`): the PID
step against the recording, and the slider moves."""

from __future__ import annotations

import math

import numpy as np

from jaxcart.metrics import SETTLING_BAND
from jaxcart.plots import plot_runs, reference_run
from tuning.lab.context import HANDOUT_B_EQ, V_SAT
from tuning.lab.model import render_source, run, seconds
from tuning.lab.part_v import OVERSHOOT_SPEC, SETTLING_SPEC, PIDResult


def render(lab, r: PIDResult) -> None:
    """Part (v)'s section."""
    lab.doc.heading("Part (v): the PID design")
    render_source(lab.doc, r.recording, "pid")
    _step(lab, r)
    _slider(lab, r)


def _label(r) -> str:
    if r.recording is None:
        return "simulated, tuned gains"
    return "simulated, the recording's gains" if not r.same else "simulated, same gains"


def _step(lab, r) -> None:
    doc, c, tuned, m = lab.doc, r.controller, r.tuned, r.model
    rows = []
    if r.info_rec is not None:
        rows.append([f"measured ({r.source})"] + metrics_row(r.info_rec))
    rows.append([f"{_label(r)}, fitted model"] + metrics_row(r.info_sim))
    if r.info_tuned is not None:
        rows.append(["simulated, pre-lab tuned gains, fitted model"] + metrics_row(r.info_tuned))
    rel = _step_figure(lab, r)
    gains_text = (
        f"kp = {c.kp:.4g} V/m, kd = {c.kd:.4g} V s/m, ki = {c.ki:.4g} V/(m s), tau = {c.tau:g} s"
    )
    if r.recording is None:
        whose = f"Gains simulated (the pre-lab's tuned PID): {gains_text}."
    elif r.same:
        whose = f"Gains of the experiment, the pre-lab's tuned PID: {gains_text}."
    else:
        whose = (
            f"Gains of the experiment: {gains_text}. These are **not** the pre-lab's tuned "
            f"gains (kp = {tuned.kp:.4g} V/m, kd = {tuned.kd:.4g} V s/m, ki = "
            f"{tuned.ki:.4g} V/(m s)), which the last row simulates on the same model."
        )
    doc.paragraph(
        f"{whose} The simulation uses the fitted model (B_eq = {m.B_eq:.3f} kg/s, "
        f"f_c = {m.f_c:.3f} N, ±6 V saturation) and the exact simulator. Design problem: "
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
    what = "experiment and simulations" if r.recording is not None else "simulation"
    doc.figure(rel, f"Part (v): PID step, {what}, position and voltage.")


def _step_figure(lab, r) -> str:
    sim, c, rec = r.sim, r.controller, r.recording
    runs = [reference_run(sim.time, sim.reference)]
    if rec is not None:
        label = f"experiment ({r.source})"
        runs.append(run(label, rec.time, rec.position, rec.command, role="experiment"))
    runs.append(run(f"{_label(r)} (fitted model)", sim.time, sim.position, sim.command))
    if r.sim_tuned is not None:
        s = r.sim_tuned
        label = "simulated, pre-lab tuned gains (fitted model)"
        runs.append(run(label, s.time, s.position, s.command))
    path, rel = lab.figure_path("part5_pid_step")
    r_final = float(np.asarray(r.experiment.signal)[-1])
    plot_runs(
        runs,
        title=f"Part (v): PID kp = {c.kp:.4g} V/m, kd = {c.kd:.4g} V s/m, "
        f"ki = {c.ki:.4g} V/(m s); step {r_final:g} m",
        path=path,
        v_limit=V_SAT,
        band=SETTLING_BAND,
        zoom=True,
    )
    return rel


def _slider(lab, r) -> None:
    doc, tuned, s = lab.doc, r.tuned, r.slider
    path, rel = lab.figure_path("part5_slider")
    plot_runs(
        [
            reference_run(s.time, s.reference, "slider (reference r)"),
            run("simulated, tuned gains, fitted model", s.time, s.position, s.command),
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
                seconds(info.settling_time),
                f"{info.steady_state_error * 1e3:.3g}",
            ]
            for i, (a, b, info) in enumerate(r.moves)
        ],
        numeric=[False, True, True, True, True, True, True],
    )
    if r.failing:
        doc.note(_failing_note(r))
    doc.figure(rel, "Part (v): the slider moves simulated with the tuned gains.")


def _failing_note(r) -> str:
    failing, m = r.failing, r.model
    worst = max(info.overshoot for _, info in failing)
    slowest = max(info.settling_time for _, info in failing)
    why = []
    if worst >= OVERSHOOT_SPEC:
        why.append(f"overshoot up to {worst:.2f} %, above the {OVERSHOOT_SPEC:g} % allowed")
    if not slowest < SETTLING_SPEC:
        why.append(
            f"settling time up to {seconds(slowest)} s, not under {SETTLING_SPEC:g} s"
            if math.isfinite(slowest)
            else f"a move that {seconds(slowest)}"
        )
    return (
        f"Move{'s' if len(failing) > 1 else ''} "
        + ", ".join(str(i) for i, _ in failing)
        + f" miss{'' if len(failing) > 1 else 'es'} the design problem ({'; '.join(why)}): "
        f"the gains were tuned on the handout's model (B_eq = {HANDOUT_B_EQ} kg/s, a 0.5 m "
        f"step) and these moves run on the fitted one (B_eq = {m.B_eq:.3f} kg/s, "
        f"f_c = {m.f_c:.3f} N) with 0.2 and 0.4 m steps. Retune on the fitted model "
        f"(`jaxcart tune --plant PLANT.toml`) or robustly (`jaxcart tune --robust`)."
    )


def metrics_row(info) -> list[str]:
    return [
        f"{info.rise_time:.3f}",
        f"{info.overshoot:.2f}",
        seconds(info.settling_time),
        f"{info.steady_state_error * 1e3:.3g}",
        "yes" if info.meets() else "no",
    ]
