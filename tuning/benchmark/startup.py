"""Fixed costs, measured the way a user meets them: each command in a new process.

``python -m tuning.benchmark.startup`` runs each case several times in fresh interpreters and
prints the
median wall time, plus the time the command reports itself (the tuner's "first gains meeting
it after", the fit's "fitted in"):

- ``import``: ``import jaxcart`` (public names load on first use) beside ``import jax``.
- ``tune``: ``jaxcart tune`` to the lab specification, cold (an empty cache folder: every
  program traced and compiled) and warm (the same folder after one run: traced programs and
  compilations on disk, :mod:`jaxcart.aot` and :mod:`jaxcart.cache`).
- ``fit-tap``, ``fit-p50``: ``jaxcart fit`` of the built-in tap and P (k = 50) recordings,
  cold and warm.

Ratios are of medians measured in the same run (warm over cold, jaxcart over jax). Each run
gets its own cache folder under a temporary directory, so the user's cache is not touched.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

CASES = ("import", "tune", "fit-tap", "fit-p50")

#: What a command prints of its own time [s].
_REPORTED = {
    "tune": re.compile(r"first gains meeting it after ([0-9.]+) s"),
    "fit": re.compile(r"fitted in ([0-9.]+) s"),
}


def _data(name: str) -> str:
    """The built-in recording ``name`` (jaxcart/data/NAME.toml, beside tuning/)."""
    return str(Path(__file__).resolve().parents[2] / "jaxcart" / "data" / f"{name}.toml")


def _command(case: str, out: Path) -> list[str]:
    jaxcart = [sys.executable, "-m", "tuning"]
    if case == "tune":
        return [*jaxcart, "tune", "--out", str(out / "gains.json"), "--force"]
    if case.startswith("fit-"):
        recording = _data(case.split("-", 1)[1])
        return [*jaxcart, "fit", recording, "--quiet", "--json", str(out / "fit.json"), "--force"]
    raise ValueError(case)


@dataclass(frozen=True)
class Timing:
    """One command run in a new process: wall time [s], CPU time [s] (user + sys of it and
    the processes it waited for), its output (stdout then stderr) and exit status."""

    wall: float
    cpu: float
    text: str
    returncode: int


def timed(cmd: list[str], env: dict, *, ok=(0,), timeout: float = 900) -> Timing:
    """Run ``cmd`` in a new process; RuntimeError (with its stderr's tail) unless its exit
    status is one of ``ok``. Commands are run one at a time (the CPU time is the growth of
    this process's waited-for children's)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
    seconds = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode not in ok:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return Timing(seconds, cpu, proc.stdout + proc.stderr, proc.returncode)


def _run(cmd: list[str], env: dict) -> tuple[float, str]:
    t = timed(cmd, env)
    return t.wall, t.text


def _reported(case: str, text: str) -> float | None:
    m = _REPORTED["tune" if case == "tune" else "fit"].search(text)
    return float(m.group(1)) if m else None


def _env(cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX", "XDG_CACHE"))}
    env["XDG_CACHE_HOME"] = str(cache)
    env.pop("JAXCART_NO_CACHE", None)
    return env


def measure(cases=CASES, repeats: int = 3, progress=None) -> dict:
    """{case: {mode: {"wall": median s, "reported": median s or None, "runs": [...]}}}."""
    say = progress or (lambda text: None)
    result: dict = {}
    with tempfile.TemporaryDirectory(prefix="jaxcart-startup-") as tmp:
        tmp = Path(tmp)
        for case in cases:
            if case == "import":
                rows = {}
                for mode, stmt in (("jax", "import jax"), ("jaxcart", "import jaxcart")):
                    runs = [
                        _run([sys.executable, "-c", stmt], _env(tmp / "none"))[0]
                        for _ in range(repeats)
                    ]
                    rows[mode] = {"wall": statistics.median(runs), "runs": runs}
                    say(f"import {mode}: {rows[mode]['wall']:.2f} s")
                result[case] = rows
                continue
            cold, warm = [], []
            for k in range(repeats):
                cache = tmp / f"{case}-{k}"
                out = tmp / f"{case}-{k}-out"
                out.mkdir(parents=True)
                # Cold: an empty cache folder; warm: the same folder, filled by the cold run.
                cold.append(_run(_command(case, out), _env(cache)))
                warm.append(_run(_command(case, out), _env(cache)))
                say(f"{case} run {k + 1}: cold {cold[-1][0]:.1f} s, warm {warm[-1][0]:.1f} s")
            rows = {}
            for mode, runs in (("cold", cold), ("warm", warm)):
                reported = [_reported(case, text) for _, text in runs]
                rows[mode] = {
                    "wall": statistics.median(s for s, _ in runs),
                    "reported": statistics.median(reported) if None not in reported else None,
                    "runs": [s for s, _ in runs],
                }
            result[case] = rows
    return result


def table(result: dict) -> str:
    lines = [f"{'case':<10} {'mode':<8} {'wall [s]':>9} {'reported [s]':>13}  ratio"]
    for case, rows in result.items():
        first = None
        for mode, row in rows.items():
            reported = row.get("reported")
            ratio = "" if first is None else f"{row['wall'] / first:.2f}x of {list(rows)[0]}"
            first = row["wall"] if first is None else first
            rep = f"{reported:13.2f}" if reported is not None else f"{'':13}"
            lines.append(f"{case:<10} {mode:<8} {row['wall']:9.2f} {rep}  {ratio}")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tuning.benchmark.startup",
        description="Fixed costs of jaxcart commands, each in a new process (median of runs).",
    )
    parser.add_argument("--cases", default=",".join(CASES), help=f"of {', '.join(CASES)}")
    parser.add_argument("--repeats", type=int, default=3, help="runs per case (default 3)")
    parser.add_argument("--json", metavar="OUT", help="also write the result as JSON")
    args = parser.parse_args(argv)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown or args.repeats < 1:
        parser.error(f"--cases: use {', '.join(CASES)}; --repeats: 1 or more")
    result = measure(cases, args.repeats, progress=lambda t: print(t, file=sys.stderr))
    print(table(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
