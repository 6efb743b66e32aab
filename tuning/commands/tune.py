"""``jaxcart tune``: tune the PID by gradient descent through the smoothed simulator, re-check
on the exact one, and write a gains file, a figure and (optionally) a JSON summary.

    jaxcart tune                                   # the lab's design problem
    jaxcart tune --free kp,kd --settling 0.9       # a PD controller, tighter settling bound
    jaxcart tune --start 60,1,4                    # from kp = 60, ki = 1, kd = 4 (handout order)
    jaxcart tune --robust --out robust.json        # meet the spec for a whole set of plants
    jaxcart tune --plant fitted.toml --f-c 0.4
    jaxcart tune --plant cart_plant.toml --robust  # for the cart as measured: robust over the
                                                   # file's standard errors, with the band
    jaxcart tune --compare                         # benchmark against Nelder-Mead and a grid
    jaxcart tune --robust --starts 64 --coordinator node0:12345 --num-processes 4 --process-id 0
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from hw.control_law import PID, setting_problem
from hw.gains import GainsFileError, write_gains
from hw.jsonio import write_json
from jaxcart.errors import UserError
from jaxcart.outputs import OUT_DIR, check_writable, free_names
from jaxcart.plots import Run, plot_runs, reference_run, run_from_response
from tuning.commands.options import (
    GAINS,
    add_cluster_options,
    add_robust_options,
    check_step,
    in_words,
    parse_gains,
    robust_ranges,
    seconds_text,
    timed,
)
from tuning.design.settings import DEFAULT  # (no jax: read while the parser is built)

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).

#: What --free may name (tuning.design.losses.PARAM_NAMES, without importing jax for --help),
#: the gains in the handout's order.
PARAMS = GAINS + ("tau", "kb", "v_limit")
UNITS = {"kp": "V/m", "ki": "V/(m s)", "kd": "V s/m", "tau": "s", "kb": "1/s", "v_limit": "V"}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "tune",
        help="tune the PID gains by gradient (default: the lab's design problem)",
        description=(
            "Tune the canonical PID by gradient descent (optax) through the smoothed "
            "simulator: first meet the specification (settling time in the 2 % band, "
            "overshoot), then drive the settling time down; every result is re-checked on "
            "the exact simulator. Default: step 0.5 m, settling < 1 s, overshoot < 5 %, 6 V, "
            "handout plant, from kp=40, ki=5, kd=5. Writes the gains file (every controller "
            "setting), a step-response figure with voltage, and prints the smooth and exact "
            "metrics. Without --out, files go to ./jaxcart-out/ under names that never "
            "overwrite. Gains are written in the handout's order: kp, ki, kd."
        ),
    )
    _output_options(p)
    _spec_options(p.add_argument_group("specification"))
    _controller_options(p.add_argument_group("controller"))
    _plant_options(p.add_argument_group("plant (design model)"))
    add_robust_options(
        p.add_argument_group("robust tuning"),
        robust_help="meet the spec on a set of plants: B_eq in [3, 7] kg/s, f_c in [0, 1] N, "
        "M within +/-10 %% (change with --range)",
    )
    _run_options(p.add_argument_group("run"))
    add_cluster_options(p)
    p.set_defaults(func=run)


def _output_options(p) -> None:
    p.add_argument(
        "--out",
        metavar="GAINS.json",
        help="gains file (default ./jaxcart-out/gains.json, gains-2.json, ...)",
    )
    p.add_argument(
        "--json",
        metavar="OUT.json",
        help='write {"gains", "exact", "smooth", "seconds", ...} here ("-": stdout)',
    )
    p.add_argument(
        "--plot",
        metavar="TUNE.png",
        help="step-response figure (default: beside the gains file, .png)",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing output files")


def _spec_options(spec) -> None:
    spec.add_argument(
        "--step", type=float, default=0.5, metavar="M", help="reference step [m] (default 0.5)"
    )
    spec.add_argument(
        "--settling",
        type=float,
        default=1.0,
        metavar="S",
        help="settling-time bound, 2 %% band [s] (default 1.0)",
    )
    spec.add_argument(
        "--overshoot",
        type=float,
        default=5.0,
        metavar="PCT",
        help="overshoot bound [%%] (default 5)",
    )
    spec.add_argument(
        "--horizon",
        type=float,
        metavar="S",
        help="simulated time [s] (default max(3, 3 x settling))",
    )


def _controller_options(ctl) -> None:
    ctl.add_argument(
        "--start",
        metavar="KP,KI,KD",
        help="starting gains in the handout's order [V/m, V/(m s), V s/m] (default 40,5,5; "
        "gains that are not free start, and stay, at 0)",
    )
    ctl.add_argument(
        "--free",
        default="kp,ki,kd",
        metavar="NAMES",
        help="parameters to tune among kp,ki,kd,tau,kb,v_limit, e.g. kp,kd for a PD "
        "controller (default kp,ki,kd); the others keep their --start / option value",
    )
    ctl.add_argument(
        "--bound",
        dest="bounds",
        action="append",
        default=[],
        metavar="NAME=LO,HI",
        help="search box of a parameter, e.g. kp=0.01,1000 (defaults: kp from 0.01 V/m up to "
        "what the cart's drive allows, its voltage or current limit over 2 %% of the step: "
        "600 V/m for 6 V and 0.5 m; kd from 0.001 V s/m up to the encoder ripple's bound; ki "
        "0.001..200 V/(m s), tau 1e-4..0.1 s, kb 0.01..1000 1/s, v_limit 0.5..6 V; the "
        "printout names the limit that binds); repeatable",
    )
    ctl.add_argument(
        "--sample-time",
        dest="sample_time",
        type=float,
        default=0.001,
        metavar="S",
        help="controller sample time [s] (default 0.001)",
    )
    ctl.add_argument(
        "--derivative-on",
        dest="derivative_on",
        default="error",
        choices=("error", "measurement"),
        help="derivative of (default error)",
    )
    ctl.add_argument(
        "--anti-windup",
        dest="anti_windup",
        default="none",
        choices=("none", "clamping", "back_calculation"),
        help="anti-windup (default none, as the lab's Simulink block)",
    )
    ctl.add_argument(
        "--tau",
        type=float,
        default=0.01,
        metavar="S",
        help="derivative filter time constant [s] (default 0.01)",
    )
    ctl.add_argument(
        "--kb",
        type=float,
        default=1.0,
        metavar="PER_S",
        help="back-calculation anti-windup gain [1/s] (default 1)",
    )
    ctl.add_argument(
        "--v-limit",
        dest="v_limit",
        type=float,
        default=6.0,
        metavar="V",
        help="software voltage limit [V] (default 6)",
    )


def _plant_options(plant) -> None:
    plant.add_argument(
        "--plant",
        dest="plant_file",
        metavar="FILE",
        help="plant file (from jaxcart fit --out or diagnose) or an experiment TOML whose "
        "[plant] applies; default: the handout's nominal plant",
    )
    plant.add_argument(
        "--B-eq",
        dest="B_eq",
        type=float,
        metavar="KG_S",
        help="viscous friction B_eq [kg/s] (handout: 5.4)",
    )
    plant.add_argument(
        "--f-c",
        dest="f_c",
        type=float,
        metavar="N",
        help="Coulomb friction in the design model [N] (default 0; slower)",
    )
    plant.add_argument(
        "--M", dest="M", type=float, metavar="KG", help="cart mass M [kg] (handout: 0.94)"
    )


def _run_options(run_) -> None:
    run_.add_argument(
        "--starts",
        type=int,
        default=DEFAULT.n_starts,
        help=f"multi-start batch size ({DEFAULT.n_starts}; rounded up to a multiple of the "
        "device count)",
    )
    run_.add_argument(
        "--iterations",
        type=int,
        default=DEFAULT.max_iterations,
        help=f"most optimizer iterations ({DEFAULT.max_iterations}; it stops earlier when done)",
    )
    run_.add_argument(
        "--seed", type=int, default=DEFAULT.seed, help=f"seed of the multi-start ({DEFAULT.seed})"
    )
    run_.add_argument(
        "--compare",
        action="store_true",
        help="benchmark: this tuner vs scipy Nelder-Mead on the exact simulator (and, for "
        "the lab problem, a quasi-random grid of equal wall time); prints ratios",
    )
    run_.add_argument(
        "--problem",
        default="lab",
        choices=("lab", "robust", "wide", "cart", "all"),
        help="with --compare: lab (kp, ki, kd, nominal plant; default), robust (25 plants), "
        "cart (all six PID numbers robust over 24 carts drawn from a fitted cart's "
        "uncertainty: --plant FILE's [fit] table, else the real recordings' cart; minutes), "
        "wide (all six PID numbers, robust over 9 plants; minutes) or all",
    )
    run_.add_argument(
        "--repeats",
        type=int,
        default=1,
        metavar="N",
        help="with --compare: each problem N times (seeds --seed ...), and the medians",
    )
    run_.add_argument("--quiet", action="store_true", help="no progress line")


def run(args) -> int:
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart import parallel

    # jax.distributed joins before any computation starts a backend.
    settings = parallel.cluster_settings(args.coordinator, args.num_processes, args.process_id)
    if settings is not None and args.compare:
        raise UserError("--compare runs in one process; drop --coordinator / --num-processes")
    outputs = None
    if settings not in (None, "auto") and settings[2] == 0:
        # Process 0's output paths are checked before it joins: a bad one fails at once
        # instead of leaving the other processes waiting for it.
        outputs = (*_outputs(args), _json_path(args))
    if not parallel.init_distributed(settings):
        return _run(args, None, outputs)
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from tuning.design.start_share import StartShare

    share = StartShare(args.starts)
    # An error one process meets from here on (an input only some hosts have, a failure
    # mid-run) is raised on every process, none waiting for a partner that has stopped.
    with share.carry():
        return _run(args, share, outputs)


def _run(args, share, outputs) -> int:
    """Tune and write the outputs. share: this process's
    :class:`tuning.design.start_share.StartShare` in a distributed run (else None); outputs:
    process 0's paths checked before it joined."""
    # lazy: imports jax, optax, scipy and matplotlib, 1.3 s at start-up (python -X importtime)
    from jaxcart import parallel
    from tuning.design.tune import tune

    problem = _problem(args)
    if args.compare:
        return _compare(args, problem)
    if problem["uncertainty"] is not None and not args.compare:
        return _for_cart(args, problem, share, outputs)
    me = parallel.process_index()
    if me == 0:
        gains_path, png_path, json_path = outputs or (*_outputs(args), _json_path(args))
    if share is not None:
        share.sync()  # every process has its inputs: an error reading them stops all now
    result = tune(
        problem["plant"],
        robust=problem["robust"],
        **_search(args, problem),
        progress=not args.quiet and me == 0,
        processes=share,
    )
    if result is None:  # another process of a distributed run: process 0 reports
        print(f"process {me} of {parallel.process_count()}: done, results sent to process 0")
        return 0
    _print_summary(result, problem["robust"] is not False, parallel.process_count())
    _write_outputs(args, result, problem, (gains_path, png_path, json_path))
    return 0 if result.meets else 1


def _for_cart(args, problem, share, outputs) -> int:
    """--robust with a plant file that knows its standard errors: the design for the cart as
    measured (robust over the file's uncertainty, with its band)."""
    # lazy: imports jax, optax, scipy and matplotlib, 1.6 s at start-up (python -X importtime)
    from tuning.design.for_cart import design_for_cart

    if share is not None:
        raise UserError(
            "tuning over a plant file's uncertainty runs in one process; drop --coordinator"
        )
    paths = outputs or (*_outputs(args), _json_path(args))
    design = design_for_cart(
        problem["uncertainty"], **_search(args, problem), progress=not args.quiet
    )
    result = design.tuned
    _print_summary(result, True, 1, design.margins)
    _print_prediction(design.prediction)
    _write_outputs(args, result, problem, paths, design)
    return 0 if result.meets else 1


def _search(args, problem) -> dict:
    """What the tuner is asked besides the plant: the problem's spec, start, free parameters,
    controller and bounds, and the search's starts, iterations and seed."""
    names = ("spec", "start", "free", "controller", "bounds")
    return {
        **{n: problem[n] for n in names},
        "n_starts": args.starts,
        "max_iterations": args.iterations,
        "seed": args.seed,
    }


def _print_prediction(p) -> None:
    """The design's band on carts drawn from the fit."""
    (s_lo, s_hi), (o_lo, o_hi) = p.interval("settling_time"), p.interval("overshoot")
    print(
        f"on {p.n} carts drawn from the plant file's uncertainty: settling "
        f"{seconds_text(s_lo)} - {seconds_text(s_hi)} ({p.level:.0%} band; the fitted cart "
        f"{seconds_text(p.nominal['settling_time'])}), overshoot {o_lo:.2f} - {o_hi:.2f} %; "
        f"meets the spec on {p.p_meet:.0%} of them"
    )


def _problem(args) -> dict:
    """The design problem from the options, every one checked before anything is computed:
    spec, free, start ({kp, ki, kd} or None), controller, plant, robust, bounds."""
    if args.starts < 1 or args.iterations < 1:
        raise UserError("--starts and --iterations must be at least 1")
    return {
        "spec": _spec(args),
        "free": _free(args.free),
        "start": _start(args.start),
        "controller": _controller(args),
        "plant": _plant(args),
        "robust": robust_ranges(args),
        "bounds": _bounds(args.bounds),
        "uncertainty": _uncertainty(args),
    }


def _uncertainty(args, *, robust=True):
    """With --robust (no --range; ``robust=False``: without) and a plant file whose [fit]
    table holds standard errors: that uncertainty
    (:func:`tuning.design.uncertainty.from_fit_table`), about the plant as the options leave
    it; else None."""
    if not ((args.robust or not robust) and not args.ranges and args.plant_file):
        return None
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.plantspec import read_plant_file
    from tuning.design.uncertainty import from_fit_table

    try:
        plant, fit = read_plant_file(args.plant_file)
    except UserError:
        return None  # an experiment file: its [plant] table has no standard errors
    if not fit:
        return None
    u = from_fit_table(plant, fit, source=f"--plant {args.plant_file}")
    return None if u is None else dataclasses.replace(u, plant=_plant(args))


def _compare(args, problem) -> int:
    """--compare: this tuner against Nelder-Mead (and a grid) on each problem; prints tables
    (with --repeats N, each problem N times, seeds seed ... seed + N - 1, and the medians)."""
    # lazy: imports jax, optax, scipy and matplotlib, 1.8 s at start-up (python -X importtime)
    from tuning.benchmark.tuners import compare_tuners, medians_table

    if problem["robust"] is not False:
        raise UserError(
            "--compare sets its own plant sets; drop --robust/--range and use --problem"
        )
    if args.repeats < 1:
        raise UserError(f"--repeats {args.repeats}: give 1 or more")
    json_path = _json_path(args)
    problems = ("lab", "robust", "wide", "cart") if args.problem == "all" else (args.problem,)
    docs = {}
    for name in problems:
        reports = []
        for k in range(args.repeats):
            report = compare_tuners(
                problem["plant"],
                problem=name,
                spec=problem["spec"],
                start=problem["start"],
                free=problem["free"] if set(problem["free"]) != set(GAINS) else None,
                controller=problem["controller"] if name not in ("wide", "cart") else None,
                seed=args.seed + k,
                bounds=problem["bounds"],
                progress=not args.quiet,
                uncertainty=_uncertainty(args, robust=False) if name == "cart" else None,
            )
            print(report["table"], flush=True)
            reports.append({k: v for k, v in report.items() if k != "table"})
        if args.repeats > 1:
            print(medians_table(reports), flush=True)
        docs[name] = reports[0] if args.repeats == 1 else reports
    if json_path is not None:
        _write_json(json_path, docs if len(docs) > 1 else docs[problems[0]])
    return 0


def _write_outputs(args, result, problem, paths, design=None) -> None:
    """The gains file (with the run's metadata: its margins, which limit binds and, for a
    design for the cart as measured, its prediction), the figure and the JSON summary."""
    # lazy: imports jax, scipy and matplotlib, 1.5 s at start-up (python -X importtime)
    from jaxcart.experiments import step
    from tuning.design.margins import margins

    gains_path, png_path, json_path = paths
    start = problem["start"]
    metadata = {
        "created_by": "jaxcart tune",
        "meets": result.meets,
        "message": result.message,
        "spec": result.spec,
        "exact": result.exact.as_dict(),
        "smooth": result.smooth.as_dict(),
        "plant": _plant_values(result.plant),
        "start": dict(start)
        if start is not None
        else "handout: kp 40, ki 5, kd 5 for the free gains, 0 for the others",
        "free": list(problem["free"]),
        "bounds": {n: list(b) for n, b in result.bounds.items()},
        "on_bound": {n: {"side": side, "bound": b} for n, (side, b) in result.on_bound.items()},
        "seconds": result.seconds,
        "binding": result.binding,
        "margins": (design.margins if design else margins(result.plant, result.gains)).to_json(),
    }
    if design is not None:
        metadata["prediction"] = design.prediction.to_json()
    if result.worst is not None:
        metadata["robust_worst"] = result.worst.as_dict()
        metadata["robust_plants"] = result.plant_set
    try:
        write_gains(gains_path, result.gains, force=args.force, **metadata)
    except GainsFileError as exc:
        raise UserError(str(exc)) from None
    spec = problem["spec"]
    sample_time = problem["controller"].sample_time
    _plot(png_path, result, step(spec.step, horizon=spec.horizon, sample_time=sample_time))
    if json_path is not None:
        _write_json(json_path, result.to_json())
    written = ", ".join(
        str(p) for p in (gains_path, png_path, json_path) if p is not None and str(p) != "-"
    )
    print(f"wrote {written}")


# ---------------------------------------------------------------- arguments


def _finite(value, flag, *, positive=False, nonnegative=False):
    if not math.isfinite(value):
        raise UserError(f"{flag} {value!r}: give a finite number")
    if positive and not value > 0:
        raise UserError(f"{flag} {value!r}: give a positive number")
    if nonnegative and not value >= 0:
        raise UserError(f"{flag} {value!r}: give a number >= 0")
    return value


def _spec(args):
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from tuning.design.losses import Spec

    _finite(args.step, "--step")
    if args.step == 0:
        raise UserError("--step 0: give a nonzero step [m], e.g. 0.5")
    _finite(args.settling, "--settling", positive=True)
    _finite(args.overshoot, "--overshoot", positive=True)
    if args.horizon is not None:
        _finite(args.horizon, "--horizon", positive=True)
        if args.horizon <= args.settling:
            raise UserError(
                f"--horizon {args.horizon}: it must exceed --settling "
                f"{args.settling} s (about 3x shows a slow creep)"
            )
    check_step(args.step)
    return Spec(
        step=args.step, settling_time=args.settling, overshoot=args.overshoot, horizon=args.horizon
    )


def _free(text):
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in PARAMS]
    if bad or not names:
        raise UserError(
            f"--free {text}: name parameters among {', '.join(PARAMS)}, e.g. --free kp,kd"
        )
    return names


def _bounds(texts):
    bounds = {}
    for text in texts:
        name, _, rest = text.partition("=")
        name = name.strip()
        try:
            lo, hi = (float(s) for s in rest.split(","))
        except ValueError:
            raise UserError(
                f"--bound {text}: write NAME=LO,HI, e.g. --bound kp=0.01,1000"
            ) from None
        if name not in PARAMS:
            raise UserError(f"--bound {text}: {name!r} is not one of {', '.join(PARAMS)}")
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise UserError(f"--bound {text}: need finite 0 < LO < HI")
        bounds[name] = (lo, hi)
    return bounds or None


def _start(text):
    """--start KP,KI,KD (the handout's order) as {kp, ki, kd}, or None."""
    return None if text is None else parse_gains(text, "--start")


def _controller(args):
    for name in ("sample_time", "tau", "kb", "v_limit"):  # the one rule (hw.control_law)
        value = getattr(args, name)
        problem = setting_problem(name, value)
        if problem:
            raise UserError(f"--{name.replace('_', '-')} {value}: {name} = {problem}")
    return PID(
        tau=args.tau,
        kb=args.kb,
        v_limit=args.v_limit,
        sample_time=args.sample_time,
        derivative_on=args.derivative_on,
        anti_windup=args.anti_windup,
    )


def _plant(args):
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.plantsource import load_plant
    from jaxcart.plantspec import build_plant, handout_plant

    plant = load_plant(args.plant_file) if args.plant_file else handout_plant()
    overrides = {}
    for name in ("B_eq", "f_c", "M"):
        value = getattr(args, name)
        if value is not None:
            flag = {"B_eq": "--B-eq", "f_c": "--f-c", "M": "--M"}[name]
            _finite(value, flag, positive=name == "M", nonnegative=True)
            overrides[name] = value
    return build_plant(overrides, base=plant, where="--B-eq / --f-c / --M")


def _outputs(args):
    """(gains path, png path), each checked writable (and refused where it exists, unless
    --force) before tuning, so a bad path fails at once, not after the computation."""
    if args.out:
        gains_path = check_writable(args.out, suffixes=(".json",), option="--out", force=args.force)
        png_path = Path(args.plot) if args.plot else gains_path.with_suffix(".png")
    else:
        gains_path, png_path = free_names(OUT_DIR, "gains", (".json", ".png"))
        gains_path = check_writable(gains_path, option="output", force=args.force)
        png_path = Path(args.plot) if args.plot else png_path
    option = "--plot" if args.plot else "figure"
    png_path = check_writable(
        png_path, suffixes=(".png", ".svg", ".pdf"), option=option, force=args.force
    )
    return gains_path, png_path


def _json_path(args):
    if args.json is None:
        return None
    if args.json == "-":
        return "-"
    return check_writable(args.json, option="--json", force=args.force)


def _write_json(path, doc):
    write_json(path, doc, force=True)  # the name was checked (or --force given) before tuning


# ---------------------------------------------------------------- output


def _plant_values(plant) -> dict:
    return {name: float(plant.get(name)) for name in plant.param_names()}


def _fmt(value, unit="", digits=3):
    value = float(value)
    if not math.isfinite(value):
        return "inf"
    return f"{value:.{digits}f}{unit}"


def _print_summary(result, robust, n_processes=1, margins=None):
    # lazy: imports jax, scipy and matplotlib, 1.5 s at start-up (python -X importtime)
    from tuning.design.margins import margins as margins_of

    g = result.gains
    print(
        f"tuned gains: kp = {g.kp:.4g} V/m, ki = {g.ki:.4g} V/(m s), kd = {g.kd:.4g} V s/m"
        f"  (tau {g.tau:g} s, derivative on {g.derivative_on}, anti-windup "
        f"{g.anti_windup}, v_limit {g.v_limit:g} V, Ts {g.sample_time:g} s)"
    )
    # Settling last: a run that never settles says so in words, past the aligned columns.
    print(f"{'':24s}{'rise [s]':>10s}{'overshoot [%]':>15s}{'ss error [m]':>14s}  settling")
    rows = [("smooth simulator", result.smooth), ("exact simulator", result.exact)]
    if robust and result.worst is not None:
        rows.append((f"worst of {len(result.plant_set)} plants", result.worst))
    for label, info in rows:
        print(
            f"{label:24s}{_fmt(info.rise_time):>10s}{_fmt(info.overshoot, digits=2):>15s}"
            f"{_fmt(info.steady_state_error, digits=5):>14s}  {seconds_text(info.settling_time)}"
        )
    print(in_words(result.message))
    print(in_words(f"what limits the gains: {result.binding}"))
    note = result.bound_note(widen=_bound_flags(result))
    if note is not None:
        print(note)
    for line in (margins or margins_of(result.plant, result.gains)).lines():
        print(in_words(f"margins: {line}" if line.startswith("gain") else line))
    to_spec = (
        ""
        if result.seconds_to_spec is None
        else f"; first gains meeting it after {result.seconds_to_spec:.1f} s"
    )
    where = f" over {n_processes} processes" if n_processes > 1 else ""
    print(
        f"{result.iterations} iterations x {result.n_starts} starts{where} in "
        f"{result.seconds:.1f} s (compilation included){to_spec}"
    )


def _bound_flags(result) -> str:
    """--bound options that widen, 4x, each bound a result sits on."""
    flags = []
    for name, (side, _) in result.on_bound.items():
        lo, hi = result.bounds[name]
        lo, hi = (lo, hi * 4) if side == "upper" else (lo / 4, hi)
        flags.append(f"--bound {name}={lo:g},{hi:g}")
    return " ".join(flags)


def _plot(path, result, experiment):
    """The exact simulator's step response (and the worst plant of a robust set). The smooth
    run at the final widths is not drawn: it lies on the exact one (the printed metrics give
    both), and simulating it here cost a compilation and seconds of eager operations."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.exact import simulate_exact

    g, spec = result.gains, result.spec
    exact = simulate_exact(result.plant, g, experiment)
    t = np.asarray(exact.time)
    r = float(spec.step)
    band = spec.band * abs(r)
    runs = [
        reference_run(t, np.asarray(exact.reference)),
        Run(f"±{100 * spec.band:g} % band", t, np.full(t.shape, r + band), role="reference"),
        Run("_band", t, np.full(t.shape, r - band), role="reference"),
        run_from_response(
            exact,
            f"exact simulator ({timed('settling', result.exact.settling_time)}, "
            f"overshoot {_fmt(result.exact.overshoot, digits=2)} %)",
        ),
    ]
    if result.plant_set:
        worst = max(
            range(len(result.plant_set)), key=lambda i: _sort_key(result.plant_set[i]["exact"])
        )
        values = result.plant_set[worst]["params"]
        # lazy: imports jax, 0.3 s at start-up (python -X importtime)
        from jaxcart.plantspec import build_plant

        worst_plant = build_plant(values, base=result.plant, check=False, where="robust set")
        run = simulate_exact(worst_plant, g, experiment)
        label = ", ".join(f"{k} {v:.3g}" for k, v in values.items())
        runs.append(run_from_response(run, f"worst plant of the set ({label})"))
    title = (
        f"jaxcart tune: kp {g.kp:.4g}, ki {g.ki:.4g}, kd {g.kd:.4g} "
        f"(spec: settling < {spec.settling_time:g} s, overshoot < {spec.overshoot:g} %)"
    )
    plot_runs(runs, title=title, path=path, voltage=True, v_limit=float(g.v_limit))


def _sort_key(metrics):
    def num(x):
        return float(x) if not isinstance(x, str) else math.inf

    return (num(metrics["settling_time"]), num(metrics["overshoot"]))
