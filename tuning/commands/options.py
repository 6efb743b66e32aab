"""What the commands share, defined once: the gain order, the robust plant set's options, the
distributed-run options (an advanced group of their own in every command's help) and how a
settling time that never comes is printed.

Like every command module it imports neither jax nor jaxcart's simulator, so ``--help`` and
argument errors answer at once.

The gains are written in the handout's order everywhere on the command line, as its PID is
written: u = kp e + ki integral(e) + kd de/dt (kp [V/m], ki [V/(m s)], kd [V s/m]).
"""

from __future__ import annotations

import argparse
import math
import re

from hw.control_law import setting_problem
from hw.handout import TRAVEL
from jaxcart.errors import UserError
from jaxcart.workers import MOST, Helpers

#: The PID gains in the handout's order.
GAINS = ("kp", "ki", "kd")
GAIN_UNITS = {"kp": "V/m", "ki": "V/(m s)", "kd": "V s/m"}
#: What a settling time of inf (the run never stays in the band) is printed as.
NOT_SETTLED = "does not settle within the horizon"
#: What a rise time of inf (the run never reaches 90 % of the step) is printed as.
NOT_RISEN = "does not rise within the horizon"
#: The title of the distributed options' group in every command's help.
ADVANCED = "advanced: distributed runs over several processes or hosts (jax.distributed)"
#: Parameters a robust set may vary (tune --range, grid --range).
ROBUST_NAMES = ("B_eq", "f_c", "M", "gamma_scale", "v_sat")


def add_cluster_options(parser: argparse.ArgumentParser) -> None:
    """--coordinator, --num-processes, --process-id (tune, grid, fit, diagnose) in a help
    group of their own, titled :data:`ADVANCED`; add it last so that it is listed last."""
    group = parser.add_argument_group(
        ADVANCED, "Not needed on one machine: a command uses every core by itself."
    )
    group.add_argument(
        "--coordinator",
        metavar="HOST:PORT",
        help="jax.distributed: address of process 0 (or JAXCART_COORDINATOR; under SLURM or "
        "Open MPI none of these is needed)",
    )
    group.add_argument(
        "--num-processes",
        metavar="N",
        help="jax.distributed: number of processes (or JAXCART_NUM_PROCESSES)",
    )
    group.add_argument(
        "--process-id",
        metavar="I",
        help="jax.distributed: this process, 0 to N-1; 0 writes the outputs (or "
        "JAXCART_PROCESS_ID)",
    )


def add_helpers_option(parser: argparse.ArgumentParser) -> None:
    """--helpers N (fit, diagnose, lab): how many helper processes make the exact simulator's
    runs several at a time (:func:`helpers`)."""
    parser.add_argument(
        "--helpers",
        type=int,
        metavar="N",
        help="helper processes that make the exact simulator's runs several at a time, "
        f"started by the command and stopped when it ends (default: one fewer than the cores, "
        f"at most {MOST}; 0: none)",
    )


def helpers(args, *, distributed: bool = False) -> Helpers:
    """The command's own :class:`jaxcart.workers.Helpers` (use it as a context manager, so
    they stop when the command ends): ``--helpers N``, else the default; none in a
    distributed run, whose processes share out the work themselves."""
    count = getattr(args, "helpers", None)
    if count is not None and count < 0:
        raise UserError(f"--helpers {count}: give a whole number of processes, 0 for none")
    return Helpers(0 if distributed else count)


def add_robust_options(group, *, robust_help: str) -> None:
    """--robust and --range (tune, grid) on ``group`` (a parser or an argument group)."""
    group.add_argument("--robust", action="store_true", help=robust_help)
    group.add_argument(
        "--range",
        dest="ranges",
        action="append",
        default=[],
        metavar="NAME=LO,HI",
        help="robust interval, e.g. B_eq=3,7 or f_c=0,0.5 or M=0.9,1.1 (M as a fraction of "
        "nominal); repeatable; replaces the default set",
    )


def robust_ranges(args):
    """--robust / --range as the design library takes them: False (not robust), True (the
    default set) or {name: (lo, hi)}."""
    if not args.robust:
        if args.ranges:
            raise UserError("--range needs --robust")
        return False
    if not args.ranges:
        return True
    ranges = {}
    for text in args.ranges:
        name, _, rest = text.partition("=")
        name = name.strip()
        try:
            lo, hi = (float(s) for s in rest.split(","))
        except ValueError:
            raise UserError(f"--range {text}: write NAME=LO,HI, e.g. --range B_eq=3,7") from None
        if name not in ROBUST_NAMES:
            raise UserError(
                f"--range {text}: {name!r} cannot vary; use B_eq, f_c, M, gamma_scale or v_sat"
            )
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
            raise UserError(f"--range {text}: need finite 0 <= LO <= HI")
        if name == "M" and lo <= 0:
            raise UserError(f"--range {text}: M is a fraction of the nominal mass, > 0")
        ranges[name] = (lo, hi)
    return ranges


def parse_gains(text: str, option: str) -> dict:
    """'KP,KI,KD' (the handout's order) -> {"kp", "ki", "kd"} [V/m, V/(m s), V s/m], each
    checked by the one rule of a PID setting (:func:`hw.control_law.setting_problem`: finite,
    >= 0)."""
    parts = [s.strip() for s in text.split(",")]
    try:
        values = [float(s) for s in parts]
    except ValueError:
        values = []
    if len(values) != 3:
        raise UserError(
            f"{option} {text}: give three gains kp,ki,kd >= 0 in the handout's order, e.g. "
            f"{option} 40,5,5"
        )
    for name, value in zip(GAINS, values, strict=True):
        problem = setting_problem(name, value)
        if problem:
            raise UserError(f"{option} {text}: {name} = {problem}")
    return dict(zip(GAINS, values, strict=True))


def check_step(step: float) -> None:
    """A step the cart can make on its track (--step of tune and grid) [m]."""
    if abs(step) > TRAVEL:
        raise UserError(f"--step {step:g}: the cart travels at most {TRAVEL:g} m on the track")


def seconds_text(value, unit: str = " s", digits: int = 3, never: str = NOT_SETTLED) -> str:
    """A time for a printed table: 'x.xxx s', or ``never`` (:data:`NOT_SETTLED`) when it is
    infinite (the metrics say inf for a moment the run never reaches)."""
    value = float(value)
    if math.isinf(value) and value > 0:
        return never
    if not math.isfinite(value):
        return "nan"
    return f"{value:.{digits}f}{unit}"


def timed(name: str, value, never: str = NOT_SETTLED) -> str:
    """'settling 0.709 s', or the whole phrase ``never`` when the time is infinite."""
    text = seconds_text(value, never=never)
    return text if text == never else f"{name} {text}"


def in_words(text: str) -> str:
    """A library's message with a settling time of inf said in words ("settling inf s",
    "settling time inf s is not under 1 s" -> :data:`NOT_SETTLED`)."""
    text = re.sub(r"settling time inf s is not under \S+ s", NOT_SETTLED, text)
    return re.sub(r"settling( time)? inf s", NOT_SETTLED, text)
