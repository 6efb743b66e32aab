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
        " for (const tr of div.querySelectorAll('tr')) { const td = tr.querySelectorAll('td');"
        " if (td.length && td[0].textContent === name) return td[2].textContent; }"
        " return null; }",
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
    plant = jc.write_plant_file(tmp_path / "P.toml", truth)
    with browser.served_app("--data", str(data), "--plant", str(plant)) as address:
        with browser.page_at(address) as page:
            assert browser.model_value(page, "kp") == 60.0  # the recording's gains
            recorded = browser.model_value(page, "recording_position", "data")
            assert len(recorded["y"]) == 3001
            nominal = browser.model_value(page, "nominal", "data")
            assert len(nominal["y"]) == 3001
            labels = page.evaluate(
                "() => { const f = Bokeh.documents[0].get_model_by_name('position_figure');"
                " return [...f.center, ...f.right].find((m) => m.items !== undefined)"
                ".items.map((item) => item.label.value); }"
            )
            assert "fitted plant" in labels and "handout plant" in labels
            assert "recorded (pid.toml)" in labels
            assert "<th>recorded</th>" in browser.model_value(page, "metrics", "text")


def test_ci_runs_the_readmes_test_command_which_provides_the_browser():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Test", 1)[1]
    command = re.search(r"^    (\S.*)$", section, re.M).group(1)
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()[-1]
    assert ci == command
    assert command.startswith("tools/provide-browser && ")
    assert os.access(ROOT / "tools" / "provide-browser", os.X_OK)
