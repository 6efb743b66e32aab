"""Every kind of figure the tool writes, written at its real size and checked by the one check
(tests/figcheck.py, run by conftest.py on every figure saved): nothing cut off at the canvas's
edges, no legend entry twice. The figures of the plotting modules: jaxcart.plots (simulate
--plot, tune, the lab's step plots), tuning.estimation.fit.plot_fit, the diagnosis's
diagnosis.png (tuning.estimation.diagnose.report), the lab's own (tuning.lab.figures), the
grid's maps (tuning.design.grid) and the class's (tuning.lab.classfigures). The commands and
the lab write them again in their own tests, checked the same way."""

from __future__ import annotations

import types
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from figcheck import figure_problems, repeated_entries

import jaxcart as jc
from jaxcart.synthetic import make_recording

#: The modules that draw the figures the tool writes, each covered below.
PLOTTING = {
    "jaxcart/plots.py",
    "tuning/estimation/fitting/plot.py",
    "tuning/estimation/diagnose/report.py",
    "tuning/estimation/diagnose/curve_report.py",
    "tuning/lab/figures.py",
    "tuning/design/grid.py",
    "tuning/lab/classfigures.py",
    "tuning/design/prediction_plot.py",
}
ROOT = Path(__file__).resolve().parents[1]


def _pixels(path) -> tuple[int, int]:
    return matplotlib.image.imread(path).shape[:2]


def test_the_check_finds_a_cut_off_legend_and_repeated_entries():
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.0, 3.0), layout="constrained")
    ax = fig.subplots()
    for k in range(4):
        ax.plot([0, 1], [k, k], label=f"a rather long legend entry number {k}")
    fig.legend(loc="outside lower center", ncols=4)
    problems = figure_problems(fig)
    assert problems and "figure legend 1 is cut off" in problems[0], problems
    assert "past the left edge" in problems[0] and "past the right edge" in problems[0]
    assert repeated_entries(["corrected (coulomb)", "corrected", "baseline", "baseline"]) == [
        "entries 'corrected (coulomb)' and 'corrected' say the same",
        "entry 'baseline' twice",
    ]
    assert repeated_entries(["fitted model (exact)", "fitted model (smooth)"]) == []


def test_every_module_that_writes_figures_is_covered_here():
    drawing = {
        str(p.relative_to(ROOT))
        for folder in ("jaxcart", "tuning")
        for p in (ROOT / folder).rglob("*.py")
        if any(w in p.read_text() for w in ("savefig(", "save_figure(", "save(fig"))
    }
    assert drawing <= PLOTTING, f"a new figure: write it in tests/test_figures.py: {drawing}"


def test_runs_figure_simulate_plot(tmp_path):
    from jaxcart.plots import Run, plot_runs, reference_run, run_from_response

    pid = jc.PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)
    exp = jc.step(0.5, horizon=3.0)
    exact = jc.simulate(jc.handout_plant(f_c=0.3), pid, exp, solver=jc.Exact())
    smooth = jc.simulate(jc.handout_plant(), pid, exp, solver=jc.Exact())
    runs = [
        Run(
            "recorded (p50_with_a_long_name.toml)",
            exact.time,
            exact.position,
            exact.command,
            role="experiment",
        ),
        reference_run(exact.time, exact.reference),
        run_from_response(smooth, "simulated (exact), the handout's plant without friction"),
    ]
    path = plot_runs(
        runs,
        title="p50.toml | kp=40, ki=5, kd=5, tau=0.01 s, v_limit=6 V",
        path=tmp_path / "run.png",
        v_limit=6.0,
        band=0.02,
        zoom=True,
    )
    assert _pixels(path) == (780, 1040)


def test_no_steady_state_inset_for_a_reference_that_keeps_moving():
    """A PD loop following a ramp to its end has no final value held: no zoom on the steady
    state (matplotlib warned of identical x limits and the inset covered the run); a step
    keeps its zoom."""
    from jaxcart.plots import reference_run, run_from_response, runs_figure

    pid = jc.PID(kp=40.0, kd=3.0)
    insets = []
    for exp in (jc.ramp(0.2, horizon=1.5), jc.step(0.2, horizon=1.5)):
        res = jc.simulate(jc.handout_plant(), pid, exp)
        runs = [reference_run(res.time, res.reference), run_from_response(res, "simulated")]
        fig = runs_figure(runs, title="run", zoom=True)
        insets.append(len(fig.axes[0].child_axes))
    assert insets == [0, 1]


@pytest.fixture(scope="module")
def two_recordings_fit():
    from jaxcart.files import read_experiment
    from tuning.estimation import fit
    from tuning.lab.data import builtin_dir

    recs = [read_experiment(builtin_dir() / f"{n}.toml") for n in ("tap", "p50")]
    quick = fit.FitSettings(widths=(1e-3, 1e-4), adam_steps=0, lm_iterations=6)
    return fit.fit(recs, ("B_eq", "f_c"), settings=quick, progress=False)


@pytest.mark.parametrize("segments", [1, 2])
def test_fit_plot(tmp_path, two_recordings_fit, segments):
    import dataclasses

    from tuning.estimation import fit

    result = dataclasses.replace(
        two_recordings_fit, segments=two_recordings_fit.segments[:segments]
    )
    path = fit.plot_fit(result, tmp_path / "fit.png")
    assert _pixels(path)[0] == 715  # 5.5 in at 130 dpi


def _diagnosis(names):
    """What plot_diagnosis reads of a Diagnosis, from exact runs of a P 50 step: the truth
    with Coulomb friction (recorded), the baseline without, the corrected model with."""
    pid = jc.PID(kp=50.0, v_limit=6.0)
    exp = jc.step(0.4, horizon=3.0)
    rec = make_recording(jc.handout_plant(f_c=0.45), pid, exp)
    base = jc.simulate(jc.handout_plant(), pid, exp, solver=jc.Exact())
    traces = [
        {
            "name": n,
            "time": rec.time,
            "measured": rec.position,
            "baseline": np.asarray(base.position),
            "after": rec.position + 1e-6,
        }
        for n in names
    ]
    windows = [{"recording": n, "start": 0.6, "end": 3.0} for n in names]
    return types.SimpleNamespace(
        traces=traces,
        chosen="coulomb",
        floor=6.6e-6,
        windows=windows,
        explained=True,
        headline="left out: coulomb (Coulomb friction f_c = 0.45 N), explained to 0.0066 mm",
    )


@pytest.mark.parametrize("names", [["p50.toml"], ["tap.toml", "p50_repeat_of_the_same.toml"]])
def test_diagnosis_figure(tmp_path, names):
    """diagnosis.png had its legend cut off at both edges, and "corrected (coulomb)" beside
    "corrected": one entry per model now, in columns the figure's width holds."""
    from tuning.estimation.diagnose.report import plot_diagnosis

    path = plot_diagnosis(_diagnosis(names), tmp_path / "diagnosis.png")
    assert _pixels(path) == (726, 715 * len(names))


def test_friction_curve_figure(tmp_path):
    """diagnose --curve's figure: both directions with their bands, an entry held (drawn
    hollow), beside the named law; the legend inside the axes, nothing repeated."""
    from tuning.estimation.diagnose.curve_report import plot_curve

    speeds = (0.0, 0.005, 0.02, 0.08, 0.32)
    d = types.SimpleNamespace(
        friction_curve={
            "named": True,
            "curve": {
                "speeds": speeds,
                "levels": {
                    "right": [0.445, 0.445, 0.445, 0.599, 0.606],
                    "left": [0.307, 0.307, 0.387, 0.448, 0.457],
                },
                "bands": {
                    "right": [0.009, 0.009, None, 0.013, 0.011],
                    "left": [0.009, 0.009, 0.013, 0.011, 0.011],
                },
                "b_eq": 4.58,
            },
        },
        parameters={"B_eq": {"value": 4.80}, "f_c": {"value": 0.479}, "f_c_asym": {"value": 0.069}},
        plant=jc.handout_plant(f_c=0.479, f_c_asym=0.069),
        chosen="coulomb_asymmetry",
    )
    path = plot_curve(d, tmp_path / "friction_curve.png")
    assert _pixels(path) == (484, 770)


def test_friction_along_the_track_figure(tmp_path):
    """diagnose --curve's figure of the position: the map through its levels, those fitted
    with their bands, those held drawn hollow, the covered stretch shaded, beside the named
    Coulomb level each way."""
    from tuning.estimation.diagnose.curve_report import plot_track

    levels = [0.4, 0.208, 0.419, 0.596, 0.4]
    d = types.SimpleNamespace(
        friction_curve={
            "track": {
                "named": True,
                "curve": {
                    "positions": [-0.2, 0.0, 0.2],
                    "levels": levels[1:4],
                    "bands": [0.012, 0.039, 0.012],
                    "knots": [-0.4, -0.2, 0.0, 0.2, 0.4],
                    "knot_values": levels,
                    "span": [-0.247, 0.285],
                },
            }
        },
        parameters={"B_eq": {"value": 4.6}, "f_c": {"value": 0.4}},
        plant=jc.handout_plant(f_c=0.4),
        chosen="coulomb",
    )
    path = plot_track(d, tmp_path / "friction_track.png")
    assert _pixels(path) == (484, 770)


def test_lab_figures(tmp_path):
    import control

    from tuning.lab import figures
    from tuning.lab.figures import Trace

    t = np.linspace(0.0, 8.0, 801)
    y = 0.2 - 0.026 - 0.174 * np.exp(-t)
    traces = [
        Trace(t, y, "recorded (p10.toml)", measured=True),
        Trace(t, y + 1e-4, "simulated (exact), fitted B_eq and f_c"),
        Trace(t, 0.2 - 0.2 * np.exp(-t), "simulated (exact), without friction"),
    ]
    hlines = [(0.2 - 0.0261, "dead band's edge: r − f_c/(k γ) = 0.1739 m", {"ls": "--"})]
    figures.time_plot(
        tmp_path / "a.png",
        traces,
        ylabel="position y [m]",
        title="Part (iii): P control, k = 10 V/m",
        hlines=hlines,
        zoom=(4.0, "the final error, zoomed"),
    )
    figures.two_panel(
        tmp_path / "b.png",
        traces,
        traces[:2],
        top_ylabel="position y [m]",
        bottom_ylabel="voltage [V]",
        title="Part (iv): PI control",
        bottom_hlines=[(6.0, "6 V limit", {"ls": ":"})],
    )
    s = control.tf("s")
    locus = control.root_locus_map(
        control.tf([1.7], [1.07, 12.3, 17.2, 0]) * (1 + 0 * s), np.linspace(0, 50, 200)
    )
    figures.root_locus(
        tmp_path / "c.png",
        locus,
        ki_bound=24.1,
        omega=3.7,
        title="Pre-lab (iii): the root locus in k_i",
    )
    assert _pixels(tmp_path / "a.png") == (550, 825)


def test_grid_maps(tmp_path):
    from tuning.design import grid

    kp, kd, ki = np.linspace(20, 150, 5), np.linspace(1, 12, 5), np.linspace(0, 10, 4)
    result = grid.grid_search(
        jc.handout_plant(), jc.PID(v_limit=6.0), jc.step(0.5, horizon=2.0), kp, kd, ki
    )
    grid.plot_slices(result, tmp_path / "grid.png")
    gains = np.array([[40.0, 5.0, 5.0], [120.0, 4.0, 1.0], [20.0, 0.5, 9.0]])
    listed = grid.evaluate_list(
        jc.handout_plant(), jc.PID(v_limit=6.0), jc.step(0.5, horizon=2.0), gains
    )
    grid.plot_slices(listed, tmp_path / "list.png")


def test_class_figures(tmp_path):
    from tuning.lab.classfigures import draw
    from tuning.lab.classroom import ClassResult, Column, Student

    t = np.linspace(0.0, 3.0, 301)
    students = []
    for k in range(12):
        s = Student(f"student-{k + 1:02d}-a-group-name", tmp_path, status="complete")
        s.results = {
            "values": {
                "B_eq_tap_fit": {"value": 4.0 + 0.1 * k},
                "f_c_tap_fit": {"value": 0.4 + 0.01 * k},
            }
        }
        s.runs = {
            "tap": (t, 0.1 * (1 - np.exp(-3 * t)) * (1 + 0.01 * k), None),
            "p_step": (t, 0.4 * (1 - np.exp(-4 * t)), np.full_like(t, 0.4)),
            "pid": (t, 0.5 * (1 - np.exp(-5 * t)), np.full_like(t, 0.5)),
        }
        students.append(s)
    students[3].marked = {"B_eq_tap_fit"}
    columns = [
        Column("B_eq_tap_fit", "B_eq, fit", "kg/s", "i"),
        Column("f_c_tap_fit", "f_c, fit", "N", "i"),
    ]
    result = ClassResult(
        tmp_path,
        tmp_path,
        students,
        columns,
        {},
        {"settling_time": 1.0, "overshoot": 5.0},
        1.0,
        1,
        False,
    )
    drawn = draw(result, tmp_path / "figures")
    assert [p.name for p, _ in drawn] == ["distributions.png", "overlays.png"]


def _prediction(tau: float, miss: float = 0.0):
    """A design's prediction for the figure: a first-order step to 0.5 m (time constant
    ``tau`` [s]) with a band of +-10 % in tau over 40 carts, 30 of which meet the spec."""
    from tuning.design.losses import Spec
    from tuning.design.prediction import Prediction

    t = np.linspace(0.0, 3.0, 3001)
    y = lambda tc: 0.5 * (1.0 - np.exp(-t / tc))  # noqa: E731
    settle = np.full(40, 4.0 * tau)
    return Prediction(
        controller=None,
        spec=Spec(),
        level=0.9,
        time=t,
        reference=np.full(t.size, 0.5),
        nominal_position=y(tau),
        nominal_command=np.zeros(t.size),
        nominal={"settling_time": 4.0 * tau},
        band=(y(1.1 * tau), y(0.9 * tau)),
        metrics={"settling_time": settle * np.linspace(0.9, 1.1, 40)},
        meets=np.arange(40) < 30,
        model_error={"settling_time": miss} if miss else {},
    )


def test_prediction_figure(tmp_path):
    """Part (v)'s designs side by side, each with its band, one with its measured run: drawn
    at its real size (tests/figcheck.py checks nothing is cut off or said twice)."""
    from tuning.design.prediction_plot import Panel, plot_predictions

    a, b = _prediction(0.15, miss=0.05), _prediction(0.2, miss=0.05)  # one cart: one miss
    measured = (a.time, 0.5 * (1.0 - np.exp(-a.time / 0.17)))
    path = plot_predictions(
        [Panel("pre-lab design", a), Panel("tuned for the cart as measured", b, measured)],
        tmp_path / "designs.png",
        title="Part (v): each design on the cart as measured",
    )
    height, width = _pixels(path)
    assert width > height > 0
