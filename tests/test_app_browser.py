"""``jaxcart app`` in a real headless browser: Debian's Chromium driven by Playwright presses the
sliders' keys like a person and sees the plot and the metrics change, the region follow ki, and
a recording and a fitted plant drawn when given.

CI provides the browser (``tools/provide-browser`` in the README's test command): there a
missing browser fails this file instead of skipping it.
"""

import os
import re
from pathlib import Path

import numpy as np
import pytest

import jaxcart as jc
from jaxcart.exact import simulate_exact
from jaxcart.synthetic import make_recording, write_recording
from tuning.app import browser

MISSING = browser.playwright_missing()
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


ROOT = Path(__file__).resolve().parents[1]


def _need_browser():
    if MISSING and IN_CI:
        pytest.fail(f"CI=true but the browser test cannot run: {MISSING}")
    if MISSING:
        pytest.skip(f"no browser here: {MISSING}")


@pytest.fixture(scope="module")
def url():
    _need_browser()
    with browser.served_app() as address:
        yield address


def _metric(page, name: str) -> str:
    """The simulated value of one metric row as the page shows it."""
    return page.evaluate(
        "(name) => { const div = document.createElement('div');"
        " div.innerHTML = Bokeh.documents[0].get_model_by_name('metrics').text;"
        " const row = [...div.querySelectorAll('tr[data-metric]')]"
        ".find((tr) => tr.dataset.metric === name);"
        " return row ? row.querySelector('td.sim').textContent : null; }",
        name,
    )


def _title(page, figure: str) -> str:
    return page.evaluate("(n) => Bokeh.documents[0].get_model_by_name(n).title.text", figure)


def test_pressing_the_sliders_changes_the_plot_and_the_metrics(url):
    requests = []
    with browser.page_at(url, requests=requests) as page:
        assert browser.model_value(page, "kp") == 40.0
        first = browser.response_data(page)
        overshoot = _metric(page, "overshoot")
        assert overshoot.endswith("%")
        # kp 40 -> 100 V/m: twelve PageUp presses of 5 V/m each (noUiSlider's keyboard).
        latencies = browser.timed_moves(page, "kp", ["PageUp"] * 12)
        assert len(latencies) == 12 and all(t > 0 for t in latencies)
        assert browser.model_value(page, "kp") == 100.0
        now = browser.response_data(page)
        assert not np.allclose(now["y"], first["y"])
        pid = jc.PID(kp=100.0, ki=5.0, kd=5.0, tau=0.01, v_limit=6.0)
        ref = simulate_exact(jc.handout_plant(), pid, jc.step(0.5, horizon=3.0))
        np.testing.assert_allclose(now["y"], ref.position, rtol=0, atol=1e-12)
        info = jc.step_info(ref, v_limit=6.0)
        assert _metric(page, "overshoot") == f"{info.overshoot:.2f} %" != overshoot
        assert browser.model_value(page, "point", "data")["kp"] == [100.0]

        # ki moves the feasible region (its image and the title's count).
        image = browser.model_value(page, "region", "data")["image"]
        assert _title(page, "region_figure").startswith("Feasible at ki = 5,")
        browser.timed_moves(page, "ki", ["PageUp"] * 4)
        assert browser.model_value(page, "ki") == 7.0
        assert _title(page, "region_figure").startswith("Feasible at ki = 7,")
        assert browser.model_value(page, "region", "data")["image"] != image

        # kd and the setpoint, down to its end (-0.8 m): the reference follows.
        browser.timed_moves(page, "kd", ["ArrowRight"] * 3)
        assert browser.model_value(page, "kd") == pytest.approx(5.3)
        browser.timed_moves(page, "setpoint", ["Home"])
        data = browser.response_data(page)
        assert data["r"][-1] == -0.8 and data["y"][-1] < -0.7
    # Offline: BokehJS and everything else came from the app's own server (no CDN).
    assert requests and all(r.startswith((url, "data:", "blob:")) for r in requests), requests


def test_a_recording_and_a_fitted_plant_are_drawn(tmp_path):
    _need_browser()
    truth = jc.build_plant({"B_eq": 4.6, "f_c": 0.45})
    rec = make_recording(truth, jc.PID(kp=60.0, ki=4.0, kd=6.0, v_limit=6.0), jc.step(0.5))
    data = write_recording(rec, tmp_path / "pid.toml")
    plant = jc.write_plant_file(tmp_path / "P.toml", truth, fit={"rms_mm": 0.2})
    with browser.served_app("--data", str(data), "--plant", str(plant)) as address:
        with browser.page_at(address) as page:
            assert browser.model_value(page, "kp") == 60.0  # the recording's gains
            recorded = browser.model_value(page, "recording_position", "data")
            assert len(recorded["y"]) == 3001
            nominal = browser.model_value(page, "nominal", "data")
            assert len(nominal["y"]) == 3001
            labels = page.evaluate(
                "() => { const f = Bokeh.documents[0].get_model_by_name('position_figure');"
                " return [...f.center, ...f.above].find((m) => m.items !== undefined)"
                ".items.map((item) => item.label.value); }"
            )
            assert "fitted plant (P.toml)" in labels and "handout plant" in labels
            assert "recorded (pid.toml)" in labels
            assert "<th>recorded</th>" in browser.model_value(page, "metrics", "text")
            # Six legend entries and a fourth metric column still fit the laptop's screen.
            _fits(page, browser.layout(page), 1280, 720)


def _fits(page, plots, width: int, height: int) -> None:
    """Nothing of the page beyond the window, nothing that scrolls; in each plot the title,
    the legends and the tick labels inside its canvas, and the tick labels apart."""
    scroll = page.evaluate(
        "() => [document.documentElement.scrollWidth, document.documentElement.scrollHeight]"
    )
    assert scroll[0] <= width and scroll[1] <= height, scroll
    assert len(plots) == 4
    for plot in plots:
        left, top, right, bottom = plot["page_box"]
        assert 0 <= left and right <= width and 0 <= top and bottom <= height, plot["name"]
        assert plot["title_width"] <= plot["title_room"], (plot["title"], plot["title_room"])
        w, h = plot["size"]
        boxes = list(plot["legends"])
        for axis in plot["axes"]:
            boxes += axis["labels"]
            d = axis["dimension"]
            # Along the axis: each label ends at least 4 px before the next begins.
            spans = sorted((b[0], b[2]) if d == 0 else (b[1], b[3]) for b in axis["labels"])
            assert len(spans) >= 3, (plot["name"], d, spans)
            gaps = [b[0] - a[1] for a, b in zip(spans, spans[1:], strict=False)]
            assert min(gaps) >= 4, (plot["name"], d, spans)
        for b in boxes:
            assert -0.5 <= b[0] and b[2] <= w + 0.5 and -0.5 <= b[1] and b[3] <= h + 0.5, (
                plot["name"],
                b,
                (w, h),
            )


def test_the_page_fits_a_laptop_screen_and_wraps_on_a_narrower_one(url):
    """At 1280 x 720 everything is on the screen with no scroll bar: the region's title and
    legend (at 1410 px wide they were off it), the poles' tick labels apart (they ran
    together). At 1000 px the right column wraps under the others, nothing off to the side."""
    with browser.page_at(url, width=1280, height=720) as page:
        plots = browser.layout(page)
        _fits(page, plots, 1280, 720)
        names = [p["name"] for p in plots]
        assert names.count("region_figure") == names.count("poles_figure") == 1
        # A click on the region lands between the sliders' steps: the gains snap to them.
        region = next(p for p in plots if p["name"] == "region_figure")
        x0, y0 = region["page_box"][:2]
        left, top, right, bottom = region["frame"]
        at_kp, at_kd = 0.613, 0.387  # fractions of the axes (kp 0-250 V/m, kd 0-20 V s/m)
        page.mouse.click(x0 + left + at_kp * (right - left), y0 + bottom - at_kd * (bottom - top))
        page.wait_for_function(
            "() => Bokeh.documents[0].get_model_by_name('point').data.kp[0] !== 40"
        )
        kp, kd = browser.model_value(page, "kp"), browser.model_value(page, "kd")
        assert kp == round(kp) and abs(kp - at_kp * 250) < 3
        assert kd == round(kd, 1) and abs(kd - at_kd * 20) < 0.3
        assert browser.model_value(page, "point", "data") == {"kp": [kp], "kd": [kd]}

        page.set_viewport_size({"width": 1000, "height": 720})
        page.wait_for_function("() => document.documentElement.scrollWidth <= 1000")
        narrow = {p["name"]: p["page_box"] for p in browser.layout(page)}
        assert all(box[2] <= 1000 for box in narrow.values())
        assert narrow["region_figure"][1] >= narrow["position_figure"][3]  # under, not beside


def test_ci_runs_the_readmes_test_command_which_provides_the_browser():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Test", 1)[1]
    command = re.search(r"^    (\S.*)$", section, re.M).group(1)
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()[-1]
    assert ci == command
    assert command.startswith("tools/provide-browser && ")
    assert os.access(ROOT / "tools" / "provide-browser", os.X_OK)
