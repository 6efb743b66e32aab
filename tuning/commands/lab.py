"""``jaxcart lab``: the whole pre-lab and lab report in one command.

    jaxcart lab                                  # built-in example recordings -> ./jaxcart-lab/
    jaxcart lab --data DIR --out REPORT_DIR      # your recordings (experiment files)
    jaxcart lab --force --out REPORT_DIR         # replace an existing report

DIR holds experiment files (TOML + CSV or .mat); each goes to its part from its kind,
controller and input, or from an index DIR/lab.toml ([recordings] tap = "tap.toml", ...).
Parts without a recording show simulations only. Writes report.md, report.html (figures
embedded), results.json, gains.json and figures/*.png (*.svg or *.pdf with --format).
"""

from __future__ import annotations

import contextlib
import signal
from pathlib import Path

from jaxcart.plots import add_format_option
from tuning.commands.options import add_helpers_option, helpers

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "lab",
        help="write the whole pre-lab and lab report (every number and plot of the handout)",
        description="Write the pre-lab and the lab report, Parts (i) to (v): appendix "
        "constants, the PI bound on k_i (Routh and root locus), a tuned PID design, B_eq and "
        "f_c fitted to the recordings, every experiment against simulations, a summary table; "
        "Markdown + self-contained HTML + results.json + figures (PNG; SVG or PDF with "
        "--format). Without --data the "
        "built-in (synthetic) example recordings are used.",
    )
    p.add_argument(
        "--data",
        metavar="DIR",
        type=Path,
        help="folder of experiment files (default: the built-in example recordings); "
        'an index DIR/lab.toml [recordings] slot = "file.toml" (slots: tap, '
        "p_step, ramp, p_error, pi, pid) wins over the guess from each file",
    )
    p.add_argument(
        "--out",
        metavar="REPORT_DIR",
        type=Path,
        help="report folder (default ./jaxcart-lab, or ./jaxcart-lab-N if it exists)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="overwrite the report in an existing, non-empty --out folder",
    )
    p.add_argument(
        "--plant",
        metavar="PLANT.toml",
        help="starting model (a plant file from fit or diagnose): its B_eq, f_c and effects; "
        "the parts refit B_eq and f_c from the recordings",
    )
    p.add_argument(
        "--no-diagnosis",
        action="store_true",
        help="leave out the section that diagnoses each recording (most of the run time)",
    )

    add_format_option(p)

    add_helpers_option(p)
    p.set_defaults(func=run)


def run(args) -> int:
    # lazy: imports jax, scipy and matplotlib, 1.7 s at start-up (python -X importtime)
    from tuning.lab.report import run_lab

    plant = None
    if args.plant:
        # lazy: imports jax, 0.3 s at start-up (python -X importtime)
        from jaxcart.plantsource import load_plant

        plant = load_plant(args.plant)
    # A killed job removes its half-written report too; the helpers stop with the command.
    with _terminate_as_interrupt(), helpers(args) as pool:
        run_lab(
            args.data,
            args.out,
            force=args.force,
            plant=plant,
            diagnosis=not args.no_diagnosis,
            fmt=args.format or "png",
            executor=pool,
        )
    return 0


@contextlib.contextmanager
def _terminate_as_interrupt():
    """SIGTERM (a scheduler's or ``kill``'s stop) raises KeyboardInterrupt like Ctrl-C, so the
    report's staging folder is removed on the way out."""

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, interrupt)
    except ValueError:  # not the main thread: leave the default
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
