"""``jaxcart bench``: simulations per second of workload W1, jaxcart beside its peers.

    jaxcart bench [--json OUT] [--batch N] [--quick]

Prints a table (sims/s and jaxcart's ratio to python-control, scipy and vectorized numpy, all
measured in this process; jaxcart in float32 and float64 as a fraction of the "c-kernel"
ceiling, a C kernel of W1 built with the system's compiler, per CPU-second; the device kind
and count) and a progress line per stage on stderr. Without a C compiler the ceiling row is
skipped and says why. Every peer is first checked
to compute the same loop as jaxcart (positions within 1e-6 m of float64 jaxcart); a peer that
does not stops the benchmark with exit status 1. ``--json OUT`` writes the whole result
(an existing file is kept unless --force).
"""

from __future__ import annotations

import sys
from pathlib import Path

from hw.jsonio import write_json
from jaxcart.errors import UserError

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="benchmark W1 (PID step, 6 V saturation) against python-control, scipy, numpy",
        description=(
            "Simulations per second of workload W1 (PID with 6 V saturation, 0.5 m step, 3 s "
            "at 1 ms, handout plant, a batch of random gain triples): jaxcart's "
            "step_metrics_batch in float32 and float64 beside python-control, scipy solve_ivp "
            "and vectorized numpy doing the same loop, and a C kernel of W1 built with the "
            "system's C compiler as the ceiling (per CPU-second), plus gradients and a 64^3 "
            "grid; runs on every local device (CPU cores or GPUs)."
        ),
    )
    parser.add_argument(
        "--json",
        metavar="OUT",
        type=Path,
        help="write the result as JSON to OUT (an existing file is kept unless --force)",
    )
    parser.add_argument(
        "--batch",
        metavar="N",
        type=int,
        default=None,
        help="gain triples for jaxcart (default 131072; 16384 with --quick)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smaller batches, one run per slow peer, a 16^3 grid, no repeats",
    )
    parser.add_argument("--force", action="store_true", help="overwrite an existing --json file")
    parser.set_defaults(func=run)


def run(args) -> int:
    # lazy: imports jax, scipy and matplotlib, 1.4 s at start-up (python -X importtime)
    from tuning.benchmark import workload as bench

    if args.batch is not None and args.batch < 1:
        raise UserError(
            f"--batch {args.batch}: give a positive number of gain triples (default 131072)"
        )
    out = args.json
    if out is not None:
        if out.is_dir():
            raise UserError(
                f"--json {out}: is a directory; give a file name such as {out / 'bench.json'}"
            )
        if out.exists() and not args.force:
            raise UserError(
                f"--json {out} exists; pass --force to overwrite it or choose another name"
            )
        if not out.parent.is_dir():
            raise UserError(
                f"--json {out}: folder {out.parent} does not exist; create it or write elsewhere"
            )
    try:
        result = bench.run_bench(batch=args.batch, quick=args.quick)
    except bench.PeerDisagreement as exc:
        print(f"jaxcart bench: FAILED: {exc}", file=sys.stderr)
        return 1
    print(bench.format_table(result))
    if out is not None:
        try:
            write_json(out, bench.to_json(result), force=True)
        except OSError as exc:
            raise UserError(
                f"--json {out}: cannot write it ({exc.strerror}); choose another path"
            ) from exc
        print(f"bench: wrote {out}", file=sys.stderr)
    return 0
