"""``jaxcart grid``: evaluate a kp x ki x kd grid (or a list) of PID gains in batched calls.

    jaxcart grid                              # 64 x 64 x 64 over the default ranges
    jaxcart grid --kp 20:120:32 --ki 0:5:8    # ranges as lo:hi:n (n evenly spaced, both ends)
    jaxcart grid --gains-file list.csv        # any list: CSV columns kp, ki, kd
    jaxcart grid --robust                     # worst case over a plant set (as tune --robust)
    jaxcart grid --coordinator node0:12345 --num-processes 4 --process-id 0   # on 4 hosts

Writes an .npz of the metric arrays and a PNG of settling-time heat maps (infeasible region
hatched, best point marked), re-checks the best gains on the exact simulator and prints both.
Finished blocks are kept in a checkpoint folder (default jaxcart-out/grid-blocks/) until the
outputs are written: a killed run, started again with the same options, resumes there.
"""

from __future__ import annotations

import csv
import math
import os
import sys
from pathlib import Path

import numpy as np

import jaxcart as jc
from jaxcart.errors import UserError
from jaxcart.outputs import OUT_DIR, check_writable, free_names
from jaxcart.plots import add_format_option, figure_name
from tuning.commands.options import (
    GAIN_UNITS,
    GAINS,
    NOT_SETTLED,
    add_cluster_options,
    add_robust_options,
    check_step,
    robust_ranges,
)

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).

DEFAULT_RANGES = {"kp": "10:150:64", "ki": "0:30:64", "kd": "0:15:64"}
#: The gains' order in the design library's grid (its axes, its rows): kp, kd, ki.
LIBRARY_ORDER = ("kp", "kd", "ki")
DEFAULT_DIR = OUT_DIR
#: Bytes per point of the result arrays (6 float64 metrics, diverged, feasible, temporaries).
_BYTES_PER_POINT = 80


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "grid",
        help="evaluate a grid (or list) of PID gains: step metrics, feasible region, best point",
        description="Evaluate a kp x ki x kd grid (or a list) of PID gains on a step of the "
        "reference with the 6 V saturation: step metrics of every point, the feasible region, "
        "the best point re-checked on the exact simulator; writes an .npz and a PNG of heat maps.",
    )
    for name, unit in GAIN_UNITS.items():
        p.add_argument(
            f"--{name}",
            metavar="LO:HI:N",
            help=f"{name} range [{unit}]: N values from LO to HI (default {DEFAULT_RANGES[name]})",
        )
    p.add_argument(
        "--gains-file",
        metavar="CSV",
        help="evaluate the rows of this CSV instead of a grid: a header naming kp, ki, kd "
        "(any order), or three columns in the handout's order kp, ki, kd",
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

    add_format_option(p)
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
    add_robust_options(
        p,
        robust_help="every metric the worst over a plant set: B_eq in [3, 7] kg/s, f_c in "
        "[0, 1] N, M within +/-10 %% (corners and centre, as tune --robust; change with --range)",
    )
    run_ = p.add_argument_group("long runs")
    run_.add_argument(
        "--checkpoint",
        metavar="DIR",
        help="folder of the finished blocks, kept until the outputs are written (default "
        "grid-blocks/ beside --out); a rerun of the same problem resumes from them",
    )
    run_.add_argument(
        "--keep-blocks",
        action="store_true",
        help="keep the block files after the outputs are written",
    )
    run_.add_argument(
        "--block",
        type=int,
        default=None,
        metavar="N",
        help="points per block: the unit of checkpoints, processes and progress (65536)",
    )
    p.add_argument("--json", metavar="OUT", help="also write a summary JSON (best point, notes)")
    add_cluster_options(p)
    p.set_defaults(func=run)


def parse_range(option: str, text: str):
    """'lo:hi:n' -> n evenly spaced gains from lo to hi; a single number is one gain."""
    # lazy: imports jax and matplotlib, 0.6 s at start-up (python -X importtime)
    from tuning.design.grid import gain_axis

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
    """Rows (kp, kd, ki) (the design library's order) of a CSV: a header naming kp, ki and kd
    (any order, other columns ignored) or no header and three columns in the handout's order
    kp, ki, kd. '#' starts a comment line."""
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
        raise UserError(f"--gains-file {path}: no rows; give one gain triple kp, ki, kd per line")
    header = [c.strip().lower() for c in lines[0][1]]
    if all(_is_number(c) for c in header):
        columns = {"kp": 0, "kd": 2, "ki": 1}  # read kp, ki, kd; rows in the library's order
    else:
        missing = [n for n in GAINS if n not in header]
        if missing:
            raise UserError(
                f"--gains-file {path}: column {', '.join(missing)} missing (columns: "
                f"{', '.join(header)}); name the columns kp, ki, kd"
            )
        columns = {n: header.index(n) for n in LIBRARY_ORDER}
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


def output_paths(out, plot, force, fmt=None) -> tuple[Path, Path]:
    """The .npz and figure paths: given ones (checked not to exist unless ``force``), or the
    first free jaxcart-out/grid.npz, grid-2.npz, ... with the figure of the same name; fmt:
    the figure's format ("png", the default, "svg" or "pdf")."""
    suffix = "." + (fmt or "png")
    if out is None and plot is None:
        return free_names(DEFAULT_DIR, "grid", (".npz", suffix))
    if out is None:
        out_path = output_paths(None, None, force)[0]
    else:
        out_path = Path(out)
    plot_path = figure_name(plot, fmt) if plot is not None else out_path.with_suffix(suffix)
    if out_path == plot_path:
        raise UserError(f"--out and --plot are both {out_path}; give them different names")

    for option, path in (("--out", out_path), ("--plot", plot_path)):
        if path.exists() and not force:
            raise UserError(
                f"{option} {path} exists; pass --force to overwrite it or choose another name"
            )
        check_writable(path, option=option, force=True)
    return out_path, plot_path


def _check_args(args) -> None:
    check_step(args.step)
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


def _plants(args, plant):
    """The plant, or the robust plant set of --robust / --range (as tune builds it)."""
    # lazy: imports jax, scipy and matplotlib, 1.9 s at start-up (python -X importtime)
    from tuning.design.problem import robust_plants

    robust = robust_ranges(args)
    if robust is False:
        return plant
    plants, _values = robust_plants(plant, None if robust is True else robust)
    return plants


def run(args) -> int:
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart import parallel

    _check_args(args)
    if args.block is not None and args.block < 1:
        raise UserError(f"--block {args.block}: give a whole number of points >= 1")
    # jax.distributed joins before any computation starts a backend.
    settings = parallel.cluster_settings(args.coordinator, args.num_processes, args.process_id)
    early = None
    if settings not in (None, "auto") and settings[2] == 0:
        # Process 0's outputs are checked before it joins: a bad one fails at once instead of
        # leaving the other processes waiting for it in the runtime's barrier.
        early = (
            *output_paths(args.out, args.plot, args.force, args.format),
            _json_path(args.json, args.force),
        )
    distributed = parallel.init_distributed(settings)
    points = _points(args)
    me = parallel.process_index()
    paths = None
    if me == 0:
        paths = early or (
            *output_paths(args.out, args.plot, args.force, args.format),
            _json_path(args.json, args.force),
        )
        folder = paths[0].parent
    else:
        folder = Path(args.out).parent if args.out else DEFAULT_DIR
    checkpoint = Path(args.checkpoint) if args.checkpoint else folder / "grid-blocks"
    problem = _problem(args)
    result = _evaluate(args, points, problem, checkpoint, distributed)
    if result is None:  # another process of a distributed run: process 0 writes the outputs
        print(f"process {me}: its blocks are computed and sent to process 0")
        return 0
    # lazy: imports jax and matplotlib, 0.6 s at start-up (python -X importtime)
    from tuning.design import grid

    exact, label = grid.recheck_set(
        problem["plants"], problem["controller"], problem["experiment"], result.best_gains
    )
    _write(args, result, exact, paths)
    _report(args, result, (exact, label), points["shape"], len(problem["plants"]))
    for path in paths:
        if path is not None:
            print(f"wrote {path}")
    if args.keep_blocks:
        print(f"kept the blocks in {result.store.dir}")
    return 0


def _points(args) -> dict:
    """The gains to evaluate: {"gains": rows (kp, kd, ki) of --gains-file, or "axes": the
    kp, kd, ki axes of the grid (the design library's order); "n": points; "shape": text}."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from tuning.design import grid_blocks

    if args.gains_file is not None:
        given = [f"--{n}" for n in GAINS if getattr(args, n) is not None]
        if given:
            raise UserError(f"{', '.join(given)} and --gains-file: give a grid or a list, not both")
        gains = np.asarray(read_gains_file(args.gains_file), dtype=float)
        n = gains.shape[0]
        points = {"gains": gains, "shape": f"{n} gain triples from {args.gains_file}"}
    else:
        axes = [parse_range(f"--{g}", getattr(args, g) or DEFAULT_RANGES[g]) for g in LIBRARY_ORDER]
        n = math.prod(a.size for a in axes)
        # Said in the handout's order, kp x ki x kd.
        sizes = dict(zip(LIBRARY_ORDER, (a.size for a in axes), strict=True))
        shape = " x ".join(f"{sizes[g]} {g}" for g in GAINS) + f" = {n} points"
        points = {"axes": axes, "shape": shape}
    if args.gains_file is not None or n <= grid_blocks.FULL_LIMIT:
        _check_memory(n)  # a larger grid streams: summaries only, bounded memory
    points["n"] = n
    return points


def _problem(args) -> dict:
    """The plant (or robust set), its smoothing, the controller template and the step."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    import jax

    from jaxcart.plantsource import load_plant
    from jaxcart.plantspec import describe_plant

    plant = load_plant(args.plant) if args.plant else jc.handout_plant()
    where = _plants(args, plant)
    plants = where if isinstance(where, list) else [where]
    # Hard forms for a plant without force effects (what the real loop does); with friction
    # or other forces the smooth loop at a tenth of the default widths, re-checked exactly.
    smoothing = jc.Smoothing().scaled(0.1) if plants[0].stage("force") else jc.EXACT_FORMS
    print(f"plant: {describe_plant(plant)}", file=sys.stderr)
    if len(plants) > 1:
        print(f"plant set: worst case over {len(plants)} plants", file=sys.stderr)
    with jax.enable_x64(True):  # the reference in float64; the grid casts it to its dtype
        experiment = jc.step(args.step, horizon=args.horizon)
    return {
        "where": where,
        "plants": plants,
        "smoothing": smoothing,
        "controller": jc.PID(v_limit=6.0),
        "experiment": experiment,
    }


def _evaluate(args, points, problem, checkpoint, distributed):
    """Every point's metrics (a :class:`tuning.design.grid.GridResult`; None on a process
    other than 0 of a distributed run)."""
    # lazy: imports jax and matplotlib, 0.6 s at start-up (python -X importtime)
    import jax.numpy as jnp

    from jaxcart import parallel
    from tuning.design import grid, grid_blocks

    dtype = jnp.float64 if args.float64 else jnp.float32
    where_run = f"{len(parallel.devices())} device(s)"
    if distributed:
        where_run += f" in process {parallel.process_index()} of {parallel.process_count()}"
    common = dict(
        dtype=dtype,
        progress=grid.progress_line("grid", devices=where_run),
        smoothing=problem["smoothing"],
        checkpoint=checkpoint,
        block=args.block or grid_blocks.BLOCK,
        say=lambda text: print(text, file=sys.stderr),
        settling_time=args.settling,
        overshoot=args.overshoot,
    )
    print(f"evaluating {points['shape']}, {np.dtype(dtype).name}, {where_run}", file=sys.stderr)
    design = (problem["where"], problem["controller"], problem["experiment"])
    if "gains" in points:
        return grid.evaluate_list(*design, points["gains"], **common)
    return grid.grid_search(*design, *points["axes"], **common)


def _write(args, result, exact, paths) -> None:
    # lazy: imports jax and matplotlib, 0.6 s at start-up (python -X importtime)
    from tuning.design import grid

    out_path, plot_path, json_path = paths
    for path in (out_path, plot_path):
        path.parent.mkdir(parents=True, exist_ok=True)
    grid.save_npz(result, out_path, exact=exact, force=args.force)
    grid.plot_slices(result, plot_path, force=args.force)
    if json_path is not None:
        grid.save_json(result, json_path, exact=exact, force=args.force)
    if not args.keep_blocks:
        result.store.remove()


def _report(args, result, checked, shape: str, n_plants: int) -> None:
    """The printed summary: feasible points, the best gains, grid against exact, speed."""
    # lazy: imports jax and matplotlib, 0.6 s at start-up (python -X importtime)
    from tuning.design import grid

    exact, label = checked
    print(f"grid: {shape}, {result.dtype}, step {args.step:g} m, horizon {args.horizon:g} s")
    if n_plants > 1:
        print(f"metrics: the worst over {n_plants} plants of the robust set")
    print(
        f"feasible: {result.n_feasible} of {result.n_points} points "
        f"(settling < {args.settling:g} s, overshoot < {args.overshoot:g} %)"
    )
    head = "best gains" if result.best_feasible else "no feasible point; closest to the spec"
    print(f"{head}: {grid.describe_gains(result.best_gains)}")
    for note in grid.edge_notes(result):
        print(f"  on a bound: {note}")
    print(_not_settled_in_words(grid.comparison(result, exact, label)))
    others = result.n_points - result.n_computed
    if result.n_computed:
        print(
            f"throughput: {result.n_computed} points in {result.elapsed:.2f} s = "
            f"{result.points_per_second:,.0f} points/s (compilation included)"
            + (f"; {others} points from the checkpoint or other processes" if others else "")
        )
    else:
        print(f"all {others} points from the checkpoint {result.store.dir}")


def _not_settled_in_words(table: str) -> str:
    """The comparison table with a settling time of inf said in words (the design library
    writes the number)."""
    lines = []
    for line in table.splitlines():
        if line.lstrip().startswith("settling time") and " inf" in line:
            line = line.replace(" inf", f" {NOT_SETTLED}")
        lines.append(line)
    return "\n".join(lines)


def _json_path(json, force):
    if json is None:
        return None

    path = Path(json)
    if path.exists() and not force:
        raise UserError(
            f"--json {path} exists; pass --force to overwrite it or choose another name"
        )
    return check_writable(path, option="--json", force=True)
