"""``jaxcart grid``: evaluate a kp x kd x ki grid (or a list) of PID gains in batched calls.

    jaxcart grid                              # 64 x 64 x 64 over the default ranges
    jaxcart grid --kp 20:120:32 --ki 0:5:8    # ranges as lo:hi:n (n evenly spaced, both ends)
    jaxcart grid --gains-file list.csv        # any list: CSV columns kp, kd, ki

Writes an .npz of the metric arrays and a PNG of settling-time heat maps (infeasible region
hatched, best point marked), re-checks the best gains on the exact simulator and prints both.
"""

from __future__ import annotations

import csv
import math
import os
import sys
from pathlib import Path

from jaxcart.errors import UserError
from jaxcart.outputs import OUT_DIR, free_names

DEFAULT_RANGES = {"kp": "10:150:64", "kd": "0:15:64", "ki": "0:30:64"}
DEFAULT_DIR = OUT_DIR
#: Bytes per point of the result arrays (6 float64 metrics, diverged, feasible, temporaries).
_BYTES_PER_POINT = 80


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "grid",
        help="evaluate a grid (or list) of PID gains: step metrics, feasible region, best point",
        description="Evaluate a kp x kd x ki grid (or a list) of PID gains on a step of the "
        "reference with the 6 V saturation: step metrics of every point, the feasible region, "
        "the best point re-checked on the exact simulator; writes an .npz and a PNG of heat maps.",
    )
    for name, unit in (("kp", "V/m"), ("kd", "V s/m"), ("ki", "V/(m s)")):
        p.add_argument(
            f"--{name}",
            metavar="LO:HI:N",
            help=f"{name} range [{unit}]: N values from LO to HI (default {DEFAULT_RANGES[name]})",
        )
    p.add_argument(
        "--gains-file",
        metavar="CSV",
        help="evaluate the rows of this CSV (columns kp, kd, ki) instead of a grid",
    )
    p.add_argument("--step", type=float, default=0.5, help="step of the reference [m] (0.5)")
    p.add_argument("--horizon", type=float, default=3.0, help="simulated time [s] (3)")
    p.add_argument(
        "--settling",
        type=float,
        default=1.0,
        help="specification: settling time below this [s] (1)",
    )
    p.add_argument(
        "--overshoot", type=float, default=5.0, help="specification: overshoot below this [%%] (5)"
    )
    p.add_argument("--out", help="metrics file (.npz); default jaxcart-out/grid.npz, grid-2.npz...")
    p.add_argument("--plot", help="heat-map PNG; default beside --out with the suffix .png")
    p.add_argument(
        "--float64",
        action="store_true",
        help="evaluate in float64 (default float32, about twice as fast)",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.add_argument(
        "--plant",
        metavar="PLANT.toml",
        help="design model: a plant file (fit --out, diagnose) or an experiment file whose "
        "[plant] applies; default the handout's nominal plant",
    )
    p.set_defaults(func=run)


def parse_range(option: str, text: str):
    """'lo:hi:n' -> n evenly spaced gains from lo to hi; a single number is one gain."""
    from tuning.grid import gain_axis

    parts = text.split(":")
    example = DEFAULT_RANGES.get(option.lstrip("-"), "10:150:64")
    how = f"use {option} LO:HI:N with 0 <= LO <= HI and N >= 1 (e.g. {option} {example})"
    if len(parts) == 1:
        parts = [parts[0], parts[0], "1"]
    if len(parts) != 3:
        raise UserError(f"{option} {text!r}: {how}")
    try:
        lo, hi = float(parts[0]), float(parts[1])
        n = int(parts[2])
    except ValueError:
        raise UserError(f"{option} {text!r}: not numbers; {how}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise UserError(f"{option} {text!r}: the bounds must be finite; {how}")
    if lo < 0 or hi < 0:
        raise UserError(f"{option} {text!r}: gains must not be negative; {how}")
    if lo > hi:
        raise UserError(f"{option} {text!r}: LO {lo:g} is above HI {hi:g}; {how}")
    if n < 1:
        raise UserError(f"{option} {text!r}: N = {n} points; {how}")
    if n == 1 and lo != hi:
        raise UserError(
            f"{option} {text!r}: one point cannot span {lo:g} to {hi:g}; "
            f"give N >= 2 or a single value ({option} {lo:g})"
        )
    return gain_axis(lo, hi, n)


def read_gains_file(path) -> list[tuple[float, float, float]]:
    """Rows (kp, kd, ki) of a CSV: a header naming kp, kd and ki (any order, other columns
    ignored) or no header and the three columns in that order. '#' starts a comment line."""
    import numpy as np

    path = Path(path)
    try:
        with open(path, newline="") as f:
            lines = [
                (i, row)
                for i, row in enumerate(csv.reader(f), start=1)
                if row and any(c.strip() for c in row) and not row[0].lstrip().startswith("#")
            ]
    except FileNotFoundError:
        raise UserError(f"--gains-file {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"--gains-file {path}: cannot read it ({exc})") from None
    if not lines:
        raise UserError(f"--gains-file {path}: no rows; give one gain triple kp, kd, ki per line")
    header = [c.strip().lower() for c in lines[0][1]]
    if all(_is_number(c) for c in header):
        columns = {"kp": 0, "kd": 1, "ki": 2}
    else:
        missing = [n for n in ("kp", "kd", "ki") if n not in header]
        if missing:
            raise UserError(
                f"--gains-file {path}: column {', '.join(missing)} missing (columns: "
                f"{', '.join(header)}); name the columns kp, kd, ki"
            )
        columns = {n: header.index(n) for n in ("kp", "kd", "ki")}
        lines = lines[1:]
    rows = []
    for line, row in lines:
        values = []
        for name, j in columns.items():
            cell = row[j].strip() if j < len(row) else ""
            try:
                value = float(cell)
            except ValueError:
                raise UserError(
                    f"--gains-file {path}, line {line}, column {name}: {cell!r} is not a number"
                ) from None
            if not np.isfinite(value) or value < 0:
                raise UserError(
                    f"--gains-file {path}, line {line}, column {name}: {cell}; "
                    "gains must be finite and not negative"
                )
            values.append(value)
        rows.append(tuple(values))
    if not rows:
        raise UserError(f"--gains-file {path}: a header but no rows")
    return rows


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def output_paths(out, plot, force) -> tuple[Path, Path]:
    """The .npz and .png paths: given ones (checked not to exist unless ``force``), or the
    first free jaxcart-out/grid.npz, grid-2.npz, ... with the PNG of the same name."""
    if out is None and plot is None:
        return free_names(DEFAULT_DIR, "grid", (".npz", ".png"))
    if out is None:
        out_path = output_paths(None, None, force)[0]
    else:
        out_path = Path(out)
    plot_path = Path(plot) if plot is not None else out_path.with_suffix(".png")
    if out_path == plot_path:
        raise UserError(f"--out and --plot are both {out_path}; give them different names")
    for option, path in (("--out", out_path), ("--plot", plot_path)):
        if path.exists() and not force:
            raise UserError(
                f"{option} {path} exists; pass --force to overwrite it or choose another name"
            )
    return out_path, plot_path


def _check_args(args) -> None:
    checks = (
        ("--step", args.step, math.isfinite(args.step) and args.step != 0, "a nonzero distance"),
        (
            "--horizon",
            args.horizon,
            math.isfinite(args.horizon) and args.horizon > 0,
            "a positive time",
        ),
        (
            "--settling",
            args.settling,
            math.isfinite(args.settling) and args.settling > 0,
            "a positive time",
        ),
        (
            "--overshoot",
            args.overshoot,
            math.isfinite(args.overshoot) and args.overshoot > 0,
            "a positive percentage",
        ),
    )
    for option, value, ok, what in checks:
        if not ok:
            raise UserError(f"{option} {value}: give {what}")
    if args.horizon <= args.settling:
        raise UserError(
            f"--horizon {args.horizon:g} s: it must be longer than --settling "
            f"{args.settling:g} s, or settling cannot be checked"
        )


def _check_memory(n_points: int) -> None:
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return
    need = n_points * _BYTES_PER_POINT
    if need > physical / 2:
        raise UserError(
            f"{n_points} points need about {need / 2**30:.1f} GiB for their metrics; "
            f"this machine has {physical / 2**30:.1f} GiB: use fewer points"
        )


def run(args) -> int:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxcart as jc
    from tuning import grid

    _check_args(args)
    if args.gains_file is not None:
        given = [f"--{n}" for n in DEFAULT_RANGES if getattr(args, n) is not None]
        if given:
            raise UserError(f"{', '.join(given)} and --gains-file: give a grid or a list, not both")
        gains = np.asarray(read_gains_file(args.gains_file), dtype=float)
        n_points = gains.shape[0]
    else:
        axes = [
            parse_range(f"--{n}", getattr(args, n) or DEFAULT_RANGES[n]) for n in DEFAULT_RANGES
        ]
        n_points = math.prod(a.size for a in axes)
    _check_memory(n_points)
    out_path, plot_path = output_paths(args.out, args.plot, args.force)

    from jaxcart.plantspec import describe_plant, load_plant

    plant = load_plant(args.plant) if args.plant else jc.handout_plant()
    # Hard forms for a plant without force effects (what the real loop does); with friction
    # or other forces the smooth loop at a tenth of the default widths, re-checked exactly.
    smoothing = jc.Smoothing().scaled(0.1) if plant.stage("force") else jc.EXACT_FORMS
    print(f"plant: {describe_plant(plant)}", file=sys.stderr)
    controller = jc.PID(v_limit=6.0)
    with jax.enable_x64(True):  # the reference in float64; the grid casts it to its dtype
        experiment = jc.step(args.step, horizon=args.horizon)
    dtype = jnp.float64 if args.float64 else jnp.float32
    spec = dict(settling_time=args.settling, overshoot=args.overshoot)
    progress = grid.progress_line("grid")
    if args.gains_file is not None:
        shape = f"{n_points} gain triples from {args.gains_file}"
        print(
            f"evaluating {shape}, {np.dtype(dtype).name}, {len(jax.devices())} device(s)",
            file=sys.stderr,
        )
        result = grid.evaluate_list(
            plant,
            controller,
            experiment,
            gains,
            dtype=dtype,
            progress=progress,
            smoothing=smoothing,
            **spec,
        )
    else:
        shape = " x ".join(str(a.size) for a in axes) + f" = {n_points} points"
        print(
            f"evaluating {shape}, {np.dtype(dtype).name}, {len(jax.devices())} device(s)",
            file=sys.stderr,
        )
        result = grid.grid_search(
            plant,
            controller,
            experiment,
            *axes,
            dtype=dtype,
            progress=progress,
            smoothing=smoothing,
            **spec,
        )
    exact, label = grid.recheck(plant, controller, experiment, result.best_gains)

    for path in (out_path, plot_path):
        path.parent.mkdir(parents=True, exist_ok=True)
    grid.save_npz(result, out_path, exact=exact, force=args.force)
    grid.plot_slices(result, plot_path, force=args.force)

    print(f"grid: {shape}, {result.dtype}, step {args.step:g} m, horizon {args.horizon:g} s")
    print(
        f"feasible: {result.n_feasible} of {result.n_points} points "
        f"(settling < {args.settling:g} s, overshoot < {args.overshoot:g} %)"
    )
    head = "best gains" if result.best_feasible else "no feasible point; closest to the spec"
    print(f"{head}: {grid.describe_gains(result.best_gains)}")
    for note in grid.edge_notes(result):
        print(f"  note: {note}")
    print(grid.comparison(result, exact, label))
    print(
        f"throughput: {result.n_points} points in {result.elapsed:.2f} s = "
        f"{result.points_per_second:,.0f} points/s (compilation included)"
    )
    print(f"wrote {out_path}")
    print(f"wrote {plot_path}")
    return 0
