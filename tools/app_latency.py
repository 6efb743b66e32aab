"""How fast the design page answers a slider move, in a real browser.

    .venv/bin/python tools/app_latency.py [--moves 40] [--json OUT.json]

Starts ``jaxcart app`` (a server process, as a student runs it), opens the page in headless
Chromium (tuning.app.browser) and presses slider keys one at a time; each latency runs from
the key press to the animation frame after the new response reached the page. Three kinds of
move: kp (the exact run, metrics and poles; the region is kept), ki to values not seen before
(the region's 32x32 batch too), the setpoint (new reference and spec lines). Prints the median
and the 90th percentile of each, with the load average of the machine while it ran (other
work on the cores shows up in the figures), and, for scale, the page's own computation of one
move measured in this process without a browser.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tuning.app import browser  # noqa: E402


def _moves(page, name: str, keys) -> list[float]:
    return browser.timed_moves(page, name, keys)


def _summary(values) -> dict:
    values = sorted(values)
    p90 = values[min(len(values) - 1, int(round(0.9 * (len(values) - 1))))]
    return {"n": len(values), "median_ms": statistics.median(values), "p90_ms": p90}


def _compute_only(repeats: int) -> dict:
    """The server's share of a kp move and of a ki move, in this process (no browser)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from bokeh.document import Document

    from tuning.app.design import DesignProblem
    from tuning.app.view import build

    page = build(Document(), DesignProblem())
    out = {}
    for name, step in (("kp", 1.0), ("ki", 0.1)):
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            page.sliders[name].value = page.sliders[name].value + step
            times.append(1e3 * (time.perf_counter() - t))
        out[name] = _summary(times)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--moves", type=int, default=40, help="key presses per kind (40)")
    parser.add_argument("--json", metavar="OUT.json", help="also write the figures here")
    args = parser.parse_args(argv)
    missing = browser.playwright_missing()
    if missing:
        print(f"app_latency: {missing}", file=sys.stderr)
        return 2
    n = args.moves
    load_before = os.getloadavg()
    with browser.served_app() as url, browser.page_at(url) as page:
        _moves(page, "kp", ["ArrowRight"] * 5)  # warm: the browser's first paints
        kp = _moves(page, "kp", ["ArrowRight", "ArrowLeft"] * (n // 2))
        ki = _moves(page, "ki", ["ArrowRight"] * n)  # each a ki not seen before
        setpoint = _moves(page, "setpoint", ["ArrowLeft", "ArrowRight"] * (n // 2))
    load_after = os.getloadavg()
    result = {
        "browser": {"kp": _summary(kp), "ki": _summary(ki), "setpoint": _summary(setpoint)},
        "compute_only": _compute_only(n),
        "loadavg_1min": [load_before[0], load_after[0]],
        "cores": os.cpu_count(),
    }
    for kind, s in result["browser"].items():
        print(
            f"{kind:9s} move, browser: median {s['median_ms']:.1f} ms, "
            f"90th percentile {s['p90_ms']:.1f} ms ({s['n']} moves)"
        )
    for kind, s in result["compute_only"].items():
        print(f"{kind:9s} move, computation alone: median {s['median_ms']:.1f} ms")
    print(
        f"load average (1 min) {load_before[0]:.2f} before, {load_after[0]:.2f} after, "
        f"on {os.cpu_count()} cores"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
