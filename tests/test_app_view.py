"""The design page's Bokeh document without a server or browser (tuning.app.view): slider
changes redraw the response, metrics, region and poles from tuning.app.design; the overlays
appear when given. (tests/test_app_browser.py drives the served page in Chromium.)"""

import numpy as np
import pytest
from bokeh.document import Document
from bokeh.events import Tap

import jaxcart as jc
from jaxcart.exact import simulate_exact
from jaxcart.synthetic import make_recording, write_recording
from tuning.app import design as app
from tuning.app.view import SLIDERS, build, spec_lines

POINTS = 10


@pytest.fixture(scope="module")
def problem():
    return app.DesignProblem(region_points=POINTS)


@pytest.fixture
def page(problem):
    return build(Document(), problem)


def test_sliders_in_the_handouts_order_with_its_start(page):
    assert SLIDERS == ("kp", "ki", "kd", "tau", "setpoint")
    assert [page.sliders[n].value for n in SLIDERS] == [40.0, 5.0, 5.0, 10.0, 0.5]  # tau in ms
    assert page.settings() == app.Settings()


def test_moving_kp_redraws_the_response_and_metrics(page):
    before_y = np.array(page.response.data["y"])
    before = page.metrics.text
    assert "misses: settling time" in before and "not settled" in before  # kp 40, ki 5, kd 5
    region = page.region.data["image"][0]
    page.sliders["kp"].value = 150.0
    page.sliders["kd"].value = 10.0
    pid = jc.PID(kp=150.0, ki=5.0, kd=10.0, tau=0.01, v_limit=6.0)
    ref = simulate_exact(jc.handout_plant(), pid, jc.step(0.5, horizon=3.0))
    np.testing.assert_array_equal(page.response.data["y"], ref.position)
    assert not np.array_equal(before_y, page.response.data["y"])
    assert page.metrics.text != before and "meets the spec" in page.metrics.text
    assert page.point.data == {"kp": [150.0], "kd": [10.0]}
    assert page.region.data["image"][0] is region  # kp, kd moves send no new region


def test_moving_ki_and_tau_recompute_the_region(page, problem):
    page.sliders["ki"].value = 12.0
    page.sliders["tau"].value = 2.0  # ms
    region = problem.region_at(app.Settings(ki=12.0, tau=0.002))
    np.testing.assert_array_equal(page.region.data["image"][0], region.status)
    assert "ki = 12, tau = 2 ms" in page.figures.region.title.text


def test_setpoint_moves_the_reference_and_the_spec(page):
    page.sliders["setpoint"].value = -0.2
    assert np.all(np.asarray(page.response.data["r"]) == -0.2)
    band, bounds = spec_lines(app.SPEC, -0.2)
    assert page.spec.data == band and page.bounds.data == bounds
    assert band["lo"][0] == pytest.approx(-0.204) and bounds["ys"][0][0] == pytest.approx(-0.21)
    assert page.figures.position.legend.location == "top_right"
    page.sliders["setpoint"].value = 0.0
    assert "no step" in page.metrics.text


def test_poles_are_the_designs(page, problem):
    page.sliders["kp"].value = 60.0
    d = problem.design(page.settings())
    np.testing.assert_allclose(page.poles.data["re"], d.poles.real)
    assert "stable" in page.figures.poles.title.text


def test_a_click_on_the_region_moves_kp_and_kd_to_the_sliders_steps(page):
    """A click lands between the sliders' steps (kp 1 V/m, kd 0.1 V s/m): the gains the page
    simulates are the ones the sliders show."""
    page.figures.region._trigger_event(Tap(page.figures.region, x=168.508, y=7.5499))
    assert page.sliders["kp"].value == 169.0 and page.sliders["kd"].value == 7.5
    assert page.point.data == {"kp": [169.0], "kd": [7.5]}
    assert page.settings() == app.Settings(kp=169.0, ki=5.0, kd=7.5)
    page.figures.region._trigger_event(Tap(page.figures.region, x=-3.0, y=25.0))
    assert page.sliders["kp"].value == 0.0 and page.sliders["kd"].value == 20.0


def test_snap_puts_a_value_on_its_sliders_step():
    assert app.snap("kp", 168.508) == 169.0
    assert app.snap("kd", 0.1 * 75) == 7.5  # 7.500000000000001 in floating point
    assert app.snap("tau", 0.01234) == 0.0125
    assert app.snap("setpoint", -0.8049) == -0.8 and app.snap("setpoint", 2.0) == 0.8


def test_overlays_appear_with_a_recording_and_a_plant(tmp_path):
    truth = jc.build_plant({"B_eq": 4.6, "f_c": 0.45})
    rec = make_recording(truth, jc.PID(kp=60.0, ki=4.0, kd=6.0, v_limit=6.0), jc.step(0.5))
    data = write_recording(rec, tmp_path / "pid.toml")
    plant = jc.write_plant_file(tmp_path / "P.toml", truth)
    problem = app.problem_from_files(data, plant, region_points=POINTS)
    doc = Document()
    page = build(doc, problem)
    recorded = doc.get_model_by_name("recording_position")
    assert recorded is not None and len(recorded.data["y"]) == 3001
    assert len(page.nominal.data["y"]) == 3001  # the handout plant beside the fitted one
    labels = [item.label.value for item in page.figures.position.legend.items]
    assert "plant of P.toml" in labels and "handout plant" in labels
    assert any(label.startswith("recorded (pid.toml") for label in labels)
    assert "<th>recorded</th>" in page.metrics.text
    # The sliders start at the recording's gains, so the fitted plant's run is its truth's.
    np.testing.assert_allclose(page.response.data["y"][-1], rec.position[-1], atol=2e-4)


def test_narrow_layout_puts_region_and_poles_underneath(problem):
    page = build(Document(), problem, narrow=True)
    top, bottom = page.layout.children
    assert page.figures.position in top.children[1].children
    assert page.figures.region in bottom.children


def test_notebook_gets_bokehjs_inline_not_from_a_cdn(monkeypatch):
    """show_in_notebook: BokehJS from the installed package (offline), the narrow page."""
    from tuning.app import server

    seen = {}
    monkeypatch.setattr(server, "output_notebook", lambda **kw: seen.update(kw))
    monkeypatch.setattr(
        server, "show", lambda app, notebook_url: seen.update(app=app, url=notebook_url)
    )
    monkeypatch.setattr(server, "warm", lambda problem: None)
    server.show_in_notebook(notebook_url="localhost:8890")
    assert seen["resources"].mode == "inline" and seen["url"] == "localhost:8890"
    doc = Document()
    seen["app"](doc)
    assert doc.get_model_by_name("kp") is not None and len(doc.roots[0].children) == 2


def test_a_busy_port_is_said_before_the_page_is_computed(monkeypatch, capsys):
    """`jaxcart app --port P` with P taken: one line with the fix, before the files are read
    and the region compiles (seconds that used to come first)."""
    import socket

    from tuning.commands.main import main

    def never(*args, **kwargs):
        raise AssertionError("the page was computed before the port was checked")

    monkeypatch.setattr(app, "problem_from_files", never)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["app", "--port", str(port), "--no-browser"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--port {port}: cannot listen on 127.0.0.1:{port}" in err[0]
    assert "another server listens there" in err[0] and "--port 0 picks a free one" in err[0]
    assert main(["app", "--address", "192.0.2.1", "--port", "0", "--no-browser"]) == 2
    assert "not an address of this machine" in capsys.readouterr().err


def test_the_page_shows_the_designs_margins_and_warns_of_hunting(page):
    """Under the metric table: the margins of the slider's gains on the design plant
    (tuning.design.margins, its numbers), and in red the warning when integral action meets
    stiction."""
    from tuning.design.margins import margins

    page.sliders["kp"].value = 150.0
    m = margins(jc.handout_plant(), jc.PID(kp=150.0, ki=5.0, kd=5.0, tau=0.01, v_limit=6.0))
    text = page.metrics.text
    assert "data-metric='margins'" in text and f"phase {m.phase_margin:.1f}°" in text
    assert f"peak sensitivity {m.peak_sensitivity:.2f}" in text and f"{m.ripple:.3g} V" in text
    sticky = app.DesignProblem(
        jc.build_plant({"B_eq": 4.0, "f_c": 0.3, "f_s": 0.6}), plant_label="sticky cart",
        region_points=POINTS,
    )  # fmt: skip
    hunting = build(Document(), sticky).metrics.text
    assert "integral action with stiction hunts" in hunting and "#cf222e" in hunting
