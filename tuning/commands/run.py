"""``jaxcart run``: run a gains file on the cart (or the simulated cart) and record the run.

The same command as ``python -m hw run`` (hw/cli.py), which needs numpy only (the lab PC); this
is its entry in the full install. The recording is an experiment file that ``jaxcart fit``,
``diagnose`` and ``lab`` read as they are; the run's metrics are printed against the spec and
the simulation of the same gains (docs/hardware.md).

    jaxcart run gains.json --device sim --step 0.5
    jaxcart run gains.json --device q2_usb --slider 0.2,0,-0.2,0.2 --out part5.toml
"""

from __future__ import annotations

from pathlib import Path

from hw.cli import CommandError, add_run_arguments, run_command
from hw.devices.base import DeviceError
from hw.expfile import ExpFileError, experiment_paths
from jaxcart.errors import UserError
from jaxcart.outputs import check_writable


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "run",
        help="run a gains file on the cart (sim, q2_usb, q8_usb, replay) and record it",
        description=(
            "Run the controller of GAINS.json (every setting as tuned) on a device: the "
            "simulated cart, a Quanser board (q2_usb, q8_usb: needs Quanser's quanser.hardware "
            "API) or a replay. The simulated cart and a replay run in virtual time unless "
            "--real-time. Gains whose simulated loop is unstable or a relay at the voltage "
            "limit are refused unless --force. Safety: track limit, voltage clamp, velocity "
            "limit, encoder nan and jumps, a watchdog chosen for the machine; every way out "
            "(a fault, Ctrl-C, SIGTERM, SIGHUP, an error, a full disk) writes 0 V. The run is "
            "recorded as an experiment file (never over an existing one) and its metrics "
            "printed against the spec and the simulation of the same gains. Same as `python "
            "-m hw run` (numpy only); see docs/hardware.md."
        ),
    )
    add_run_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    if args.out:
        # Before the cart moves: an output under a file or in a read-only folder fails now.

        for path in experiment_paths(Path(args.out)):
            check_writable(path, option="--out")
    try:
        return run_command(args)
    except (CommandError, ExpFileError, DeviceError) as exc:
        raise UserError(" ".join(str(exc).split())) from None
    except ValueError as exc:  # a controller the loop refuses, or bad limits
        if isinstance(exc, UserError):
            raise
        raise UserError(" ".join(str(exc).split())) from None
