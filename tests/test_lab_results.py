"""The lab as compute, then render (tuning/lab): parts are functions of explicit inputs that
return frozen results, the fitter is an argument, rendering reads results only; and figures a
grader reads (jaxcart/plots.py, tuning/lab/figures.py): no markers over the models, one legend
off the data, distinct reference and band, a zoomed steady-state error, PNG/SVG/PDF.

The whole report's numbers and sentences are tested in tests/test_lab.py.
"""

import ast
import dataclasses
import io
import types
from pathlib import Path

import numpy as np
import pytest

from jaxcart.errors import UserError
from jaxcart.plots import Run, figure_name, plot_runs, reference_run, runs_figure
from tuning.lab import cart, fits, inputs, part_i, part_ii, part_iii, report
from tuning.lab.context import Lab, check_format
from tuning.lab.data import builtin_dir
from tuning.lab.html import Document
from tuning.lab.model import CartModel

LAB = Path(__file__).resolve().parent.parent / "tuning" / "lab"
MAGIC = {"png": b"\x89PNG", "pdf": b"%PDF", "svg": b"<?xml"}


@pytest.fixture(scope="module")
def computed():
    """Every part on the built-in recordings with a fitter that records its calls (about 15 s
    on 2 cores: the fits, the exact runs and the pre-lab's tuning; no diagnosis)."""
    import jax

    calls = []

    def spy(recordings, params, **kwargs):
        calls.append(([Path(r.path).name for r in recordings], tuple(params), kwargs))
        return fits.fit(recordings, params, **kwargs)

    found = inputs.find_inputs(builtin_dir())
    with jax.enable_x64(True):
        results = report.compute(found, CartModel(), diagnosis=False, fit=spy)
    return found, results, calls


def test_no_function_in_the_lab_is_over_100_lines():
    long = []
    for path in sorted(LAB.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > 100:
                    long.append(f"{path.name}:{node.name} ({lines} lines)")
    assert not long, long


def test_parts_use_the_fitter_they_are_given(computed):
    _, _, calls = computed
    fitted = [(names, params) for names, params, _ in calls]
    # Part (i) the tap, Part (ii) the step twice (without and with f_c held), Part (iii) the
    # ramp: every fit of the report went through the fitter passed in.
    # Then the cart once from every recording, and its driven runs alone (B_eq beside the
    # tap's): without a diagnosis, B_eq, f_c and v_sat, shared (no part was run twice).
    everything = sorted(Path(r.path).name for r in computed[0].runs())
    assert fitted[:4] == [
        (["tap.toml"], ("B_eq", "f_c")),
        (["p50.toml"], ("B_eq",)),
        (["p50.toml"], ("B_eq",)),
        (["ramp.toml"], ("f_c",)),
    ]
    assert [(sorted(n), p) for n, p in fitted[4:]] == [
        (everything, ("B_eq", "f_c", "v_sat")),
        ([n for n in everything if n != "tap.toml"], ("B_eq", "f_c", "v_sat")),
    ]


def test_results_are_frozen_and_the_model_travels_explicitly(computed):
    _, r, _ = computed
    for result in (r, r.prelab, r.part_i, r.part_ii, r.part_iii, r.part_iv, r.part_v):
        assert dataclasses.is_dataclass(result)
        with pytest.raises(dataclasses.FrozenInstanceError):
            result.recording = None
    # The model each part ran on is the one the part before returned: the tap's for (ii)
    # and (iii); (iii)'s, with the ramp's f_c, for (iv) and (v).
    tap_model = r.part_i.model
    assert r.part_ii.model is tap_model and r.part_iii.steady.model is not tap_model
    assert r.part_iii.ramp.model.B_eq == tap_model.B_eq
    assert r.part_iv.model is r.part_iii.model
    # Part (v) runs on the cart fitted once from every recording.
    assert r.part_v.model == cart.model_of(r.cart, r.part_iii.model)
    assert r.part_v.model.B_eq == r.cart.fit.params["B_eq"].value
    assert r.part_iii.model.f_c == r.part_iii.ramp.f_fit.value != tap_model.f_c
    assert r.part_v.tuned is r.prelab.gains


def test_the_prelab_and_jaxcart_tune_give_one_answer(computed, tmp_path):
    """One tuner, one answer (issue 34): the pre-lab's PID is the one ``jaxcart tune`` writes
    for the same problem, bit for bit, and the cart's re-tune searches alike: the same tuner
    with the same settings (:data:`tuning.design.settings.DEFAULT`, the command's defaults)."""
    import json

    from tuning.commands.main import build_parser, main
    from tuning.design.settings import DEFAULT

    args = build_parser().parse_args(["tune"])
    assert (args.starts, args.iterations, args.seed) == (
        DEFAULT.n_starts,
        DEFAULT.max_iterations,
        DEFAULT.seed,
    )
    _, r, _ = computed
    gains = tmp_path / "gains.json"
    assert main(["tune", "--quiet", "--out", str(gains), "--json", str(tmp_path / "t.json")]) == 0
    written = json.loads(gains.read_text())["controller"]
    assert [written[n] for n in ("kp", "ki", "kd")] == [
        r.prelab.gains.kp,
        r.prelab.gains.ki,
        r.prelab.gains.kd,
    ]
    for tuned in (r.prelab.tuned, r.cart.tuned):
        assert tuned.n_starts == DEFAULT.n_starts and tuned.iterations <= DEFAULT.max_iterations


def test_results_hold_results_never_a_thread(computed):
    """The lab's diagnosis and re-tune run in threads beside the parts: each is collected
    before the result that holds it is built, and no thread outlives the computation."""
    import threading
    from concurrent.futures import Future

    from jaxcart.background import Background

    _, r, _ = computed
    assert r.cart.tuned is not None and r.cart.tuned.meets
    for result in (r, r.prelab, r.part_v, r.cart):
        for field in dataclasses.fields(result):
            value = getattr(result, field.name)
            assert not isinstance(value, Background | Future | threading.Thread), field.name
    assert not [t.name for t in threading.enumerate() if t.name.startswith("jaxcart-")]


def test_a_part_is_a_function_of_its_inputs(computed):
    """Part (iii)'s steady state from the same model and recording gives the same numbers;
    from another model, other numbers, and the first result is unchanged."""
    found, r, _ = computed
    rec = found.recordings["p_error"]
    import jax

    with jax.enable_x64(True):
        again = part_iii.steady_state(rec, r.part_iii.model)
        other = part_iii.steady_state(rec, dataclasses.replace(r.part_iii.model, f_c=0.2))
    assert again.bound == r.part_iii.steady.bound and again.e_sim == r.part_iii.steady.e_sim
    assert other.bound == pytest.approx(0.2 / (10 * other.gamma), rel=1e-12)
    assert r.part_iii.steady.bound != other.bound


def test_rendering_reads_results_only(computed, tmp_path):
    """Two renderings of the same results into two documents are the same text, and the
    numbers of the summary come from the results (the true values from the synthetic data)."""
    found, r, _ = computed
    texts = []
    for k in range(2):
        (tmp_path / f"r{k}" / "figures").mkdir(parents=True)
        lab = Lab(out=tmp_path / f"r{k}", inputs=found, doc=Document("t"), stream=io.StringIO())
        lab.diagnosis = False
        report.render(lab, r)
        texts.append(lab.doc.to_markdown())
        assert sorted(p.name for p in (tmp_path / f"r{k}" / "figures").iterdir()) == sorted(
            Path(f).name for f in lab.figures
        )
    assert texts[0] == texts[1]
    values = {v.key: v for v in report.values(r)}
    assert values["B_eq_tap_fit"].value == r.part_i.b_fit.value
    assert values["f_c"].value == r.part_iii.model.f_c
    assert values["B_eq_tap_fit"].true(found.synthetic) == found.synthetic["B_eq"]
    assert (
        part_ii.to_json(r.part_ii, r.agreement, diagnosis=False)["B_eq_agreement"]["text"]
        in texts[0]
    )
    assert part_i.to_json(r.part_i)["c"] == pytest.approx(r.part_i.model.B_eq + 7.7236, abs=1e-4)


def test_cart_model_builds_the_plant_it_names():
    model = CartModel(B_eq=4.2, f_c=0.3)
    plant = model.plant()
    assert float(plant.B_eq) == 4.2 and float(plant.get("f_c")) == 0.3
    assert float(plant.get("v_sat")) == 6.0
    bare = model.plant(saturation=False, coulomb=False)
    assert [type(e).__name__ for e in bare.effects] == []
    assert float(model.plant(B_eq=7.0).B_eq) == 7.0


# ---------------------------------------------------------------- figures


def _runs(final_error=3e-3):
    t = np.linspace(0.0, 3.0, 3001)
    y = 0.4 * (1 - np.exp(-6 * t)) - final_error * (1 - np.exp(-6 * t))
    model = 0.4 * (1 - np.exp(-6 * t))
    return [
        reference_run(t, np.full_like(t, 0.4)),
        Run("recorded", t, y, 6 * np.exp(-6 * t), role="experiment"),
        Run("model", t, model, 6 * np.exp(-6 * t)),
    ]


def test_the_recording_does_not_hide_the_model_and_the_legend_is_off_the_data():
    fig = runs_figure(_runs(), title="t", v_limit=6.0, band=0.02)
    ax_y, ax_v = fig.axes[:2]
    recorded = [line for line in ax_y.lines if line.get_label() == "recorded"][0]
    model = [line for line in ax_y.lines if line.get_label() == "model"][0]
    assert recorded.get_marker() in ("None", None, "")  # no markers over the model line
    assert model.get_zorder() > recorded.get_zorder()  # the model drawn on top
    assert recorded.get_linewidth() > model.get_linewidth()  # a band the model sits in
    assert ax_y.get_legend() is None and ax_v.get_legend() is None
    (legend,) = fig.legends
    labels = [text.get_text() for text in legend.get_texts()]
    assert labels.count("recorded") == 1 and "±6 V limit" in labels
    assert "±2 % settling band" in labels
    # The reference is a line, the band a shaded strip: two different artists.
    ref = [line for line in ax_y.lines if line.get_label() == "reference r"][0]
    assert ref.get_linestyle() != "-" and ref.get_color() != "0.62"
    band = [p for p in ax_y.patches if p.get_label() == "±2 % settling band"]
    assert len(band) == 1


def test_zoomed_inset_shows_the_steady_state_error_in_mm():
    fig = runs_figure(_runs(final_error=3e-3), title="t", zoom=True)
    insets = fig.axes[0].child_axes
    assert len(insets) == 1
    inset = insets[0]
    low, high = inset.get_ylim()
    # The recorded 3 mm error fills the inset: within its range, the range a few mm.
    assert low < -0.1 < 3.0 < high < 10.0
    errors = {line.get_label(): line.get_ydata() for line in inset.lines}
    assert errors["recorded"][-1] == pytest.approx(3.0, abs=0.01)
    assert abs(errors["model"][-1]) < 0.01
    assert inset.get_xlim()[0] == pytest.approx(1.5)  # the second half of the run


@pytest.mark.parametrize("fmt", ["png", "svg", "pdf"])
def test_every_format_is_written(tmp_path, fmt):
    path = plot_runs(_runs(), title="t", path=tmp_path / f"f.{fmt}", zoom=True)
    assert path.read_bytes()[:5].startswith(MAGIC[fmt])


def test_figure_names_follow_the_format():
    assert figure_name("run", "pdf") == Path("run.pdf")
    assert figure_name("run.svg", "svg") == Path("run.svg")
    assert figure_name("run.png", None) == Path("run.png")
    with pytest.raises(UserError, match="--plot run.png is a .png file but --format is svg"):
        figure_name("run.png", "svg")
    assert check_format("SVG") == "svg"
    with pytest.raises(UserError, match="--format jpg"):
        check_format("jpg")


def test_the_report_page_embeds_svg_and_a_png_copy_of_a_pdf(tmp_path):
    (tmp_path / "figures").mkdir()
    found = types.SimpleNamespace(recordings={}, synthetic=None)
    lab = Lab(out=tmp_path, inputs=found, doc=Document("t"), fmt="pdf")
    targets, rel = lab.figure_path("a")
    assert rel == "figures/a.pdf" and [p.suffix for p in targets] == [".pdf", ".png"]
    plot_runs(_runs(), title="t", path=targets)
    lab.doc.figure(rel, "a")
    svg = Lab(out=tmp_path, inputs=found, doc=lab.doc, fmt="svg")
    path, rel_svg = svg.figure_path("b")
    plot_runs(_runs(), title="t", path=path)
    lab.doc.figure(rel_svg, "b")
    html = lab.doc.to_html(tmp_path)
    assert html.count("data:image/png;base64,") == 1
    assert html.count("data:image/svg+xml;base64,") == 1
    assert "](figures/a.pdf)" in lab.doc.to_markdown()


def test_diagnosis_figure_shades_the_mismatch_with_a_legend(monkeypatch, tmp_path):
    import matplotlib

    from jaxcart import plots
    from tuning.estimation.diagnose.report import plot_diagnosis

    t = np.linspace(0.0, 2.0, 2001)
    measured = 0.4 * (1 - np.exp(-5 * t))
    baseline = measured + 3e-3 * (t > 1.0)  # parts from the recording after 1 s only
    d = types.SimpleNamespace(
        traces=[
            {
                "name": "p50.toml",
                "time": t,
                "measured": measured,
                "baseline": baseline,
                "after": measured,
            }
        ],
        windows=[{"recording": "p50.toml", "start": 1.0, "end": 2.0}],
        floor=1e-5,
        chosen="coulomb",
        explained=True,
        headline="demo",
    )
    figures = []
    monkeypatch.setattr(plots, "save", lambda fig, path, dpi: figures.append(fig) or path)
    plot_diagnosis(d, tmp_path / "d.png")
    (fig,) = figures
    labels = [text.get_text() for text in fig.legends[0].get_texts()]
    for label in ("recording", "mismatch of the baseline (beyond", "windows beyond the floor"):
        assert any(label in x for x in labels), labels
    assert any(x.startswith("encoder floor ±") for x in labels)
    top, bottom = fig.axes[0], fig.axes[1]
    # The shaded mismatch is the area between baseline and recording where they part by more
    # than the floor: 3 mm for 1 s, nothing before 1 s.
    (shade,) = [c for c in top.collections if "mismatch" in c.get_label()]
    area, left = 0.0, np.inf
    for path in shade.get_paths():
        x, y = path.vertices[:, 0], path.vertices[:, 1]
        area += 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
        if np.ptp(y) > 1e-6:
            left = min(left, x.min())
    assert area == pytest.approx(3e-3, rel=0.01)
    assert left == pytest.approx(1.0, abs=2e-3)
    window = [p for p in bottom.patches if "windows" in p.get_label()]
    assert window and all(p.get_height() <= 0.05 for p in window)  # a strip, not the axis
    matplotlib.pyplot.close("all")
