"""The ``jaxcart`` command line: one subcommand per job of the lab.

Each subcommand lives in its own module with ``register(subparsers)``, which adds its parser
and sets ``func``; ``func(args)`` returns the exit status. Errors the user can fix
(:class:`UserError`) are printed as one line, without a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from hw.gains import GainsFileError
from jaxcart.errors import UserError

#: Subcommand modules, in the order ``jaxcart --help`` lists them. The application layer may
#: name tuning's commands here: the packages themselves never import upward.
COMMANDS = (
    "jaxcart.commands.simulate",
    "tuning.commands.tune",
    "tuning.commands.grid",
    "tuning.commands.fit",
    "tuning.commands.lab",
    "jaxcart.commands.bench",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxcart",
        description="Differentiable simulator and auto-tuner for the cart-on-a-track servo lab.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:  # a real missing dependency, not a command not written yet
                raise
            continue
        module.register(sub)
    return parser


def main(argv=None) -> int:
    # One XLA device per core, before jax starts, so batches shard over every core.
    from jaxcart.batch import host_devices

    host_devices()
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (UserError, GainsFileError) as exc:
        print(f"jaxcart {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
