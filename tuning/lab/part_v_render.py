"""Part (v) of the report drawn from its results: the PID step against the recording, the
slider moves (:class:`tuning.lab.part_v.PIDResult`), and the designs on the cart as measured
with their bands, margins and the measured run against its prediction
(:class:`tuning.lab.part_v_design.Designs`)."""

from __future__ import annotations

import math

import numpy as np

from hw.predicted import check_lines
from jaxcart.metrics import SETTLING_BAND
from jaxcart.plots import plot_runs, reference_run
from tuning.design.prediction import LEVEL, t_factor
from tuning.design.prediction_plot import Panel, plot_predictions
from tuning.lab.context import HANDOUT_B_EQ, V_SAT, fmt
from tuning.lab.model import render_source, run, seconds
from tuning.lab.part_v import OVERSHOOT_SPEC, SETTLING_SPEC, PIDResult


def render(lab, r: PIDResult, designs=None) -> None:
    """Part (v)'s section (``designs``: :class:`tuning.lab.part_v_design.Designs` or None)."""
    lab.doc.heading("Part (v): the PID design")
    render_source(lab.doc, r.recording, "pid")
    _step(lab, r)
    render_designs(lab, designs)
    _slider(lab, r)


def _drive_runs(runs: dict) -> str:
    """ ", each drive value as a new run's (...)": how a new run's drive values are drawn and
    from how many runs each ({name: n}; "" without any)."""
    if not runs:
        return ""
    many = [f"{n} from {k} runs" for n, k in runs.items() if k > 1]
    one = [f"{n} from 1 run, by its fit's standard error alone" for n, k in runs.items() if k == 1]
    t = (
        f"{', '.join(many)}: Student's t over the runs' own values, wide where the runs are "
        "few and differ; each step recorded again narrows it"
        if many
        else ""
    )
    return f", each drive value as a new run's ({'; '.join(x for x in (t, ', '.join(one)) if x)})"


def render_designs(lab, d) -> None:
    """The subsection: every design on the cart as measured, side by side."""
    doc = lab.doc
    doc.heading("The designs on the cart as measured", 3)
    if d is None:
        doc.note("No driven recording: there is no fitted cart to predict the designs on.")
        return
    first = d.designs[0].prediction
    doc.paragraph(
        f"Each design's 0.5 m step on the cart fitted from every recording ({d.source}), and "
        f"on {first.n} carts drawn from that fit: each fitted value from its standard error"
        f"{_drive_runs(d.drive_runs)}. The band holds "
        f"{first.level:.0%} of such carts (a run of the design lies inside it with that "
        "probability, if the cart is as the fit says); P(spec) is the chance that a run of "
        "the design settles under 1 s with under 5 % overshoot, within 6 V and the track's "
        "0.814 m, over these carts and a new run's miss of the model (below, where a step was "
        "recorded). Exact simulator throughout."
    )
    doc.table(
        ["design", "kp, ki, kd", "settling [s]", f"{first.level:.0%} band [s]", "overshoot [%]",
         f"{first.level:.0%} band [%]", "P(spec)", "measured"],
        [_prediction_row(x) for x in d.designs],
        numeric=[False, False, True, False, True, False, True, False],
    )  # fmt: skip
    _misses(lab, d)
    path, rel = lab.figure_path("part5_designs")
    plot_predictions(
        [Panel(x.label, x.prediction, x.run) for x in d.designs],
        path,
        title="Part (v): each design on the cart as measured",
    )
    doc.figure(rel, "Part (v): each design's step with its band; the measured run in grey.")
    _margins(lab, d)
    for x in d.designs:
        if x.check is not None:
            where = "inside" if x.check["inside"] else "outside"
            doc.paragraph(
                f"The measured run ({d.recording}, {x.label}) against its prediction, on its "
                f"own step and horizon: {where} the band. "
                + "; ".join(check_lines(x.check))
                + ". The run is one of the recordings the cart was fitted to (its drive limit "
                "among the runs' spread)."
            )


def _ms(seconds: float) -> str:
    """A time in milliseconds, three digits (whole ones from a second up: 1364, not 1.36e+03)."""
    ms = float(f"{seconds * 1e3:.3g}")
    return f"{ms:.3g}" if abs(ms) < 1000 else f"{seconds * 1e3:.0f}"


def _bounds(e) -> str:
    """The model error's bounds in words, each with the steps it rests on (Student's t over
    their misses; none where no step measures it)."""
    sizes = {
        "settling_time": (f"{_ms(e['settling_time'])} ms", "in time"),
        "overshoot": (f"{e['overshoot']:.3g} %", "in overshoot"),
    }
    parts = []
    for metric, (size, what) in sizes.items():
        n = e["steps"][metric]
        parts.append(
            f"{size} {what} (Student's t over {n} step{'s' if n != 1 else ''})"
            if n
            else f"nothing {what} (no step measures it)"
        )
    return " and ".join(parts)


def _misses(lab, d) -> None:
    """How far the fitted cart misses each recorded step: the model error in every band."""
    if not d.misses:
        lab.doc.paragraph(
            "No closed-loop step was recorded: the bands are the fit's alone (how far the "
            "model misses a step of this cart is not known)."
        )
        return
    e = d.model_error
    held = sum(m.held_out for m in d.misses)
    by = (
        "the cart fitted without it (each step held out of the joint fit in turn)"
        if held == len(d.misses)
        else "the fitted cart"
        if not held
        else f"the cart fitted without it where it could be held out ({held} of "
        f"{len(d.misses)}), else the fitted cart"
    )
    steps = e["steps"]
    level = d.designs[0].prediction.level if d.designs else LEVEL
    lab.doc.paragraph(
        "The fit's standard errors say how well the recordings pin the model's values, not "
        "how right the model is; the recorded steps say that. Each is simulated on "
        f"{by}, with its own controller, step and drive limit, and compared with the "
        f"recording; what a new run may miss by at the bands' level, {_bounds(e)}, widens "
        "every band above on both sides (no edge below 0), and P(spec) counts it."
        + (
            f" One step alone sets the time bound: t_{{{(1 + level) / 2:g}, 1}} = "
            f"{t_factor(1, level):.1f} times its one miss; each further recorded step "
            "narrows it."
            if steps["settling_time"] == 1
            else ""
        )
    )
    lab.doc.table(
        ["recording", "predicted by", "enters the 2 % band [s]: measured, simulated",
         "settling time [s]: measured, simulated", "overshoot [%]: measured, simulated"],
        [
            [m.name, "held out" if m.held_out else "the fit",
             f"{seconds(m.entering[0])}, {seconds(m.entering[1])}",
             f"{seconds(m.settling[0])}, {seconds(m.settling[1])}",
             f"{m.overshoot[0]:.2f}, {m.overshoot[1]:.2f}"]
            for m in d.misses
        ],
        numeric=[False, False, True, True, True],
    )  # fmt: skip


def _prediction_row(x) -> list[str]:
    p, c = x.prediction, x.controller
    (s_lo, s_hi), (o_lo, o_hi) = p.interval("settling_time"), p.interval("overshoot")
    measured = "-"
    if x.measured is not None:
        measured = f"{seconds(x.measured.settling_time)} s, {x.measured.overshoot:.2f} %"
    return [
        x.label,
        f"{c.kp:.4g}, {c.ki:.4g}, {c.kd:.4g}",
        seconds(p.nominal["settling_time"]),
        f"{seconds(s_lo)}-{seconds(s_hi) if math.isfinite(s_hi) else 'never'}",
        f"{p.nominal['overshoot']:.2f}",
        f"{o_lo:.2f}-{o_hi:.2f}",
        f"{p.p_meet:.0%}",
        measured,
    ]


def _margins(lab, d) -> None:
    """The margins of each design on the fitted cart, and the warnings they carry."""
    doc = lab.doc
    delay = d.designs[0].margins.delay
    behind = f"with its {delay * 1e3:.3g} ms delay" if delay else "(the fit has no delay)"
    doc.paragraph(
        f"Margins of each design on the fitted cart: the sampled loop (1 ms, zero-order hold) "
        f"{behind}, python-control's margins of C(z) P(z) (friction "
        "and the drive's limits left out); the ripple is how far one encoder count moves the "
        "command within a sample, kp q + kd q / (tau + Ts)."
    )
    doc.table(
        ["design", "gain margin", "phase margin [deg]", "delay margin [ms]",
         "peak sensitivity Ms", "ripple [V]"],
        [
            [x.label, _gm(x.margins), fmt(x.margins.phase_margin, 3),
             fmt(x.margins.delay_margin * 1e3, 3), fmt(x.margins.peak_sensitivity, 3),
             fmt(x.margins.ripple, 3)]
            for x in d.designs
        ],
        numeric=[False, True, True, True, True, True],
    )  # fmt: skip
    for x in d.designs:
        if x.margins.hunting:
            doc.note(f"{x.label}: {x.margins.hunting}.")


def _gm(m) -> str:
    if not math.isfinite(m.gain_margin):
        return "∞"
    return f"{m.gain_margin:.3g} ({m.gain_margin_db:.1f} dB)"


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
    plant = r.plant if r.plant is not None else m.plant()
    v_sat = float(plant.get("v_sat")) if "v_sat" in plant.param_names() else math.inf
    f_c = float(plant.get("f_c")) if "f_c" in plant.param_names() else 0.0
    own = " (the run's own drive limit)" if r.plant is not None else ""
    doc.paragraph(
        f"{whose} The simulation uses the fitted model (B_eq = {float(plant.B_eq):.3f} kg/s, "
        f"f_c = {f_c:.3f} N, ±{v_sat:.3g} V saturation{own}) and the exact simulator. Design "
        f"problem: settling < 1 s, overshoot < 5 %."
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
    doc.figure(
        rel,
        f"Part (v): PID step, {what}, position and the commanded voltage (what the software "
        "sent, clipped at its 6 V; the amplifier's own limit acts after it).",
    )


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
        f"f_c = {m.f_c:.3f} N) with 0.2 and 0.4 m steps. Retune for the cart as measured "
        f"(`jaxcart tune --plant cart_plant.toml --robust`, as the lab does for `gains.json` "
        f"where it has a driven recording)."
    )


def metrics_row(info) -> list[str]:
    return [
        f"{info.rise_time:.3f}",
        f"{info.overshoot:.2f}",
        seconds(info.settling_time),
        f"{info.steady_state_error * 1e3:.3g}",
        "yes" if info.meets() else "no",
    ]
