"""Drive the design page in headless Chromium: the browser test and the latency benchmark.

Playwright for Python (its wheel carries its driver, so it works offline) drives Debian's
Chromium at :data:`CHROMIUM`; nothing is downloaded. The page is served by a real
``jaxcart app`` process (:func:`served_app`), and sliders are moved the way a person moves them
with the keyboard: focus a slider's handle, press an arrow key.

Latency (:func:`timed_moves`): from the key press (a capture listener on ``keydown`` stamps
``performance.now()``) to the animation frame after the new response reached the page (Bokeh
paints the changed plot in the frame its data change requested, before ours).

Layout (:func:`layout`): what each plot drew where, for the test that the page fits a screen:
its place on the page, its title's width, its legends' boxes and every tick label's box.

Chromium's flags keep it off the network: without the background-networking ones it keeps
trying to reach Google's services, which floods a closed network.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

#: Debian's Chromium (``tools/provide-browser`` installs it).
CHROMIUM = "/usr/bin/chromium"
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)
#: Seconds to wait for ``jaxcart app`` to say where the page is (imports, the region's
#: compilation: about 10 s on a loaded 2-core machine).
START_TIMEOUT = 180.0
#: The page is up when Bokeh has built the document and the metric table has text.
READY = (
    "() => window.Bokeh !== undefined && Bokeh.documents.length > 0 && "
    "Bokeh.documents[0].get_model_by_name('metrics') !== null && "
    "Bokeh.documents[0].get_model_by_name('metrics').text.length > 0"
)
_URL = re.compile(r"(http://\S+/)")


def chromium() -> str | None:
    """The Chromium executable, or None when it is not installed."""
    return CHROMIUM if os.access(CHROMIUM, os.X_OK) else shutil.which("chromium")


def playwright_missing() -> str | None:
    """Why the browser cannot be driven here (one line), or None when it can."""
    try:
        # lazy: playwright may be absent (an optional dependency: .[test])
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "Playwright is not installed (pip install -e '.[test]')"
    if chromium() is None:
        return f"no Chromium at {CHROMIUM} (run tools/provide-browser as root)"
    return None


@contextlib.contextmanager
def served_app(*args: str, timeout: float = START_TIMEOUT):
    """Run ``python -m tuning app --port 0 --no-browser ARGS`` and yield the page's URL; the
    server is stopped on the way out."""
    command = [sys.executable, "-m", "tuning", "app", "--port", "0", "--no-browser", *args]
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen(
        command,
        cwd=root,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: queue.Queue = queue.Queue()
    # A thread reads the server's output so that a silent server cannot block the wait (and
    # its later lines never fill the pipe).
    pump = threading.Thread(target=_pump, args=(proc.stdout, lines), daemon=True)
    pump.start()
    try:
        yield _wait_for_url(lines, timeout)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        pump.join(timeout=10)
        proc.stdout.close()


def _wait_for_url(lines: queue.Queue, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    seen = []
    while (left := deadline - time.monotonic()) > 0:
        try:
            line = lines.get(timeout=left)
        except queue.Empty:
            break
        if line is None:  # the server ended
            break
        seen.append(line)
        found = _URL.search(line)
        if found:
            return found.group(1)
    tail = "".join(seen[-20:])
    raise RuntimeError(f"jaxcart app did not say where the page is; its output:\n{tail}")


def _pump(stream, lines: queue.Queue) -> None:
    for line in stream:
        lines.put(line)
    lines.put(None)


@contextlib.contextmanager
def page_at(
    url: str, *, width: int = 1280, height: int = 720, timeout: float = 120.0, requests=None
):
    """A Playwright page of Chromium (fresh profile, off the network) showing ``url`` in a
    window of ``width`` x ``height`` [px] (a laptop's 1280 x 720 by default: the page is made to
    fit it), once the design page is built; ``requests``: a list that gets the URL of every
    request the page makes."""
    # lazy: playwright may be absent (an optional dependency: .[test])
    from playwright.sync_api import sync_playwright

    profile = tempfile.mkdtemp(prefix="jaxcart-chromium-")
    try:
        with sync_playwright() as p:
            context = p.chromium.launch_persistent_context(
                profile,
                executable_path=chromium(),
                headless=True,
                args=list(FLAGS),
                viewport={"width": width, "height": height},
            )
            try:
                if requests is not None:
                    context.on("request", lambda request: requests.append(request.url))
                page = context.new_page()
                page.goto(url, timeout=timeout * 1e3)
                page.wait_for_function(READY, timeout=timeout * 1e3)
                yield page
            finally:
                context.close()
    finally:
        shutil.rmtree(profile, ignore_errors=True)


def model_value(page, name: str, attribute: str = "value"):
    """An attribute of the Bokeh model called ``name`` as the browser has it."""
    return page.evaluate(
        "([n, a]) => { const v = Bokeh.documents[0].get_model_by_name(n)[a];"
        " return ArrayBuffer.isView(v) ? Array.from(v) : v; }",
        [name, attribute],
    )


def response_data(page) -> dict:
    """The response source's columns (t, y, r, v) as lists."""
    return page.evaluate(
        "() => { const d = Bokeh.documents[0].get_model_by_name('response').data;"
        " const out = {}; for (const k of Object.keys(d)) out[k] = Array.from(d[k]);"
        " return out; }"
    )


def handle(page, name: str):
    """The keyboard handle of the slider called ``name`` (Playwright's CSS sees through
    Bokeh's shadow roots)."""
    return page.locator(f".slider-{name} .noUi-handle")


_LISTEN = """() => {
    if (window.__jaxcart !== undefined) { window.__jaxcart = {t0: null, lat: []}; return; }
    const src = Bokeh.documents[0].get_model_by_name('response');
    window.__jaxcart = {t0: null, lat: []};
    document.addEventListener('keydown', () => { window.__jaxcart.t0 = performance.now(); },
                              true);
    src.properties.data.change.connect(() => {
        const t0 = window.__jaxcart.t0;
        if (t0 === null) return;
        window.__jaxcart.t0 = null;
        requestAnimationFrame(() => window.__jaxcart.lat.push(performance.now() - t0));
    });
}"""


def timed_moves(page, name: str, keys, *, timeout: float = 30.0) -> list[float]:
    """Press each of ``keys`` on the slider ``name``, one at a time, each after the page showed
    the last; returns each press's latency [ms] until the new response was painted."""
    page.evaluate(_LISTEN)
    knob = handle(page, name)
    knob.focus()
    for i, key in enumerate(keys):
        knob.press(key)
        page.wait_for_function(f"() => window.__jaxcart.lat.length > {i}", timeout=timeout * 1e3)
    return page.evaluate("() => window.__jaxcart.lat")


# Tick labels are drawn on the canvas, not in the DOM: each axis's labelling policy (Bokeh calls
# its filter with every label's box before drawing) is wrapped to keep the boxes, and the axis
# is changed and changed back so that it is drawn again.
_WATCH_LABELS = """() => {
    const figures = [];
    (function walk(view) {
        if (view.renderer_views !== undefined) figures.push(view);
        for (const child of (view.child_views || [])) walk(child);
    })(...Bokeh.index.roots);
    window.__jaxcart_layout = {figures, labels: new Map()};
    for (const fig of figures) {
        for (const view of fig.renderer_views.values()) {
            if (!view.model.type.endsWith("Axis")) continue;
            const policy = view.model.major_label_policy;
            const filter = policy.filter;
            policy.filter = function (indices, boxes, distance) {
                window.__jaxcart_layout.labels.set(view, boxes.map(
                    (b) => [b.left, b.top, b.right, b.bottom]));
                return filter.call(this, indices, boxes, distance);
            };
            const tick = view.model.major_tick_out;
            view.model.major_tick_out = tick + 1;
            view.model.major_tick_out = tick;
        }
    }
}"""
_LAYOUT = """() => {
    const {figures, labels} = window.__jaxcart_layout;
    const measure = document.createElement("canvas").getContext("2d");
    const box = (b) => [b.left, b.top, b.right, b.bottom];
    return figures.map((fig) => {
        const views = [...fig.renderer_views.values()];
        const title = fig.model.title;
        measure.font = `${title.text_font_style} ${title.text_font_size} ${title.text_font}`;
        const titleView = views.find((v) => v.model === title);
        const rect = fig.el.getBoundingClientRect();
        return {
            name: fig.model.name,
            title: title.text,
            title_width: measure.measureText(title.text).width,
            title_room: titleView.bbox.width,
            page_box: [rect.left, rect.top, rect.right, rect.bottom],
            size: [fig.bbox.width, fig.bbox.height],
            frame: box(fig.frame.bbox),
            legends: views.filter((v) => v.model.type === "Legend").map((v) => box(v.bbox)),
            axes: views.filter((v) => labels.has(v)).map(
                (v) => ({dimension: v.dimension, labels: labels.get(v)})),
        };
    });
}"""


def layout(page, *, timeout: float = 30.0) -> list[dict]:
    """Each plot of the page as drawn: name, title, title_width (its text [px]), title_room
    (the width it has [px]), page_box (left, top, right, bottom on the page [px]), size (the
    canvas's width and height [px]), frame (the data's box), legends and axes (each a
    dimension, 0 for x, and the boxes of its tick labels); boxes are (left, top, right,
    bottom) in the canvas's pixels."""
    page.evaluate(_WATCH_LABELS)
    expected = page.evaluate(
        "() => window.__jaxcart_layout.figures.reduce((n, f) => n + [...f.renderer_views"
        ".values()].filter((v) => v.model.type.endsWith('Axis')).length, 0)"
    )
    page.wait_for_function(
        f"() => window.__jaxcart_layout.labels.size >= {expected}", timeout=timeout * 1e3
    )
    return page.evaluate(_LAYOUT)
