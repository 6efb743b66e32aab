"""The ``jaxcart`` command line: one subcommand per job of the lab.

The command line is the top floor of the layout (docs/design.md, "Layout"): it lives in
``tuning/`` and may import ``jaxcart/`` and ``hw/``; neither of them imports it.

Each subcommand lives in its own module with ``register(subparsers)``, which adds its parser and
sets ``func``; ``func(args)`` returns the exit status. Building the parser imports no jax (a command
module imports what imports jax, jaxcart's simulator and tuning's engines, inside its ``func``), so
``jaxcart --help`` and argument errors answer at once. Errors the user can fix
(:class:`jaxcart.errors.UserError`, :class:`hw.gains.GainsFileError`) are printed as one line,
without a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as installed

from hw.atomicio import OutputError
from hw.gains import GainsFileError
from jaxcart import xlaflags
from jaxcart.background import running
from jaxcart.cache import enable_persistent_cache
from jaxcart.errors import UserError
from jaxcart.plots import preload
from tuning.commands import interruptible

#: Subcommand modules, in the order ``jaxcart --help`` lists them: a student's first (the lab
#: report, raw files in, trying and designing gains, fitting), then the cart, the instructor's
#: class and the benchmark.
COMMANDS = (
    "tuning.commands.lab",
    "tuning.commands.examples",
    "tuning.commands.import_mat",
    "tuning.commands.simulate",
    "tuning.commands.app",
    "tuning.commands.tune",
    "tuning.commands.grid",
    "tuning.commands.fit",
    "tuning.commands.diagnose",
    "tuning.commands.run",
    "tuning.commands.classroom",
    "tuning.commands.bench",
)


def version() -> str:
    """The installed jaxcart's version (from its package metadata; imports nothing)."""
    try:
        return installed("jaxcart")
    except PackageNotFoundError:
        return "unknown (not installed; pip install -e . gives it)"


def build_parser() -> argparse.ArgumentParser:
    """The whole ``jaxcart`` parser, every subcommand registered; imports neither jax nor
    jaxcart."""
    parser = argparse.ArgumentParser(
        prog="jaxcart",
        description="Differentiable simulator and auto-tuner for the cart-on-a-track servo lab.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    parser.add_argument(
        "--no-cache",
        action="store_true",
        help="do not keep compiled programs in the user's cache folder (~/.cache/jaxcart/xla, "
        "safe to delete; also JAXCART_NO_CACHE=1)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(name).register(sub)
    return parser


#: Commands that write a figure by default (matplotlib is imported while they compute).
PLOTTING = {"tune", "lab", "class", "simulate", "diagnose", "grid"}


def main(argv=None) -> int:
    """Run the command ``argv`` (None: the process's own command line) and return its exit
    status. On the process's own command line, work a failed command leaves running in the
    background (the lab's diagnosis, inside XLA) does not outlive it: the process ends at once
    with the status, since the interpreter's shutdown would abort on that thread (status 134,
    "terminate called ...") after the one-line error."""
    status = _main(argv)
    if argv is None:
        if running():
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status)
    return status


def _main(argv) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # A command runs: on the user's behalf, before jax starts a backend, loops compiled whole on
    # a CPU (jaxcart.xlaflags; JAXCART_XLA_FLAGS=0 leaves XLA_FLAGS alone), the compilation
    # cache (--no-cache: none) and one XLA device per core, so that the loops run as kernels,
    # later runs skip compiling and batches shard over every core.

    xlaflags.request()
    if not args.no_cache:
        enable_persistent_cache()
    # lazy: imports jax, 0.3 s at start-up (python -X importtime); after parsing, not before
    from jaxcart.parallel import use_cpu_devices

    use_cpu_devices()
    preloading = None
    if args.command in PLOTTING or getattr(args, "plot", None):
        preloading = preload()
    try:
        return _run(args)
    finally:
        if preloading is not None:
            preloading.join()  # (half a second's import at most: no thread outlives a command)


def _run(args) -> int:
    """The command's exit status; a user's error is one line (status 2), Ctrl-C 130."""
    try:
        if args.command in INTERRUPTIBLE and not getattr(args, "coordinator", None):
            return int(interruptible.run(_in_float64, args) or 0)
        return int(_in_float64(args) or 0)
    except (UserError, GainsFileError, OutputError) as exc:
        print(f"jaxcart {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _in_float64(args):
    """``args.func(args)`` in float64: every command computes as the lab's tests check it
    (jax.enable_x64, scoped to the command's thread; the process's own setting is left as it
    was, and the fits, the diagnosis and the tuner scope it themselves besides)."""
    # lazy: jax costs 0.3 s at start-up (python -X importtime); building the parser imports no jax
    import jax

    with jax.enable_x64(True):
        return args.func(args)


#: Commands that spend minutes inside compiled programs: run so that Ctrl-C stops them at
#: once (tuning.commands.interruptible); a distributed run keeps its main thread.
INTERRUPTIBLE = {"fit", "diagnose", "lab"}


if __name__ == "__main__":
    sys.exit(main())
