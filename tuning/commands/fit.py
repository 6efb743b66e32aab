"""``jaxcart fit``: fit plant parameters to one or several recordings.

    jaxcart fit tap.toml --params B_eq,f_c
    jaxcart fit tap.toml p50.toml --params B_eq,f_c --classic --cross --plot fit.png \\
        --json fit.json --out fitted.toml
    jaxcart fit a.toml b.toml c.toml --cross --coordinator node0:12345 --num-processes 3 \\
        --process-id 0

Prints each parameter with its standard error (or "not identifiable"), the RMS position error
before and after (smooth and exact simulators), optionally the lab's classic estimates and the
cross-prediction of each recording from the others' fit; writes the fitted plant (``--out``,
readable by ``--plant`` of simulate, tune, grid and lab), a JSON report and an overlay plot.
Across processes (jax.distributed, :mod:`tuning.estimation.cross_fit`) each fits its share of the
recordings for ``--cross``; process 0 runs the joint fit, prints and writes.
"""

from __future__ import annotations

import sys

from hw.atomicio import all_or_none
from hw.jsonio import write_json
from jaxcart.errors import UserError
from jaxcart.outputs import check_writable
from jaxcart.plots import add_format_option, figure_name
from tuning.commands.options import add_cluster_options, add_helpers_option, helpers
from tuning.estimation import cross_fit

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).

#: Figure formats matplotlib writes (checked before fitting, not after).
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg", ".eps", ".ps", ".tif", ".tiff", ".webp")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit",
        help="fit plant parameters (B_eq, f_c, ...) to recordings, with standard errors",
        description="Fit plant parameters shared by the recordings, and each recording's start "
        "state, by gradient through the smoothed simulator and a Levenberg-Marquardt polish "
        "finished on the exact simulator. A tap's coasting part is found automatically.",
    )
    p.add_argument("experiments", nargs="+", metavar="EXPERIMENT.toml", help="recordings")
    p.add_argument(
        "--params",
        default="B_eq,f_c",
        help="parameters to fit, comma-separated: B_eq, M, gamma_scale or any effect's "
        "parameter (f_c, v_sat, f_s, delay, deadzone, k_s, y_rest, i_max, ...; naming one adds "
        "its effect); default B_eq,f_c",
    )
    p.add_argument(
        "--per-recording",
        default="",
        metavar="NAMES",
        help="of the --params, those free in each recording (a drive that differs from run to "
        "run: v_sat, i_max, gamma_scale); the others are one value for the cart; e.g. "
        "--params B_eq,f_c,v_sat --per-recording v_sat",
    )
    p.add_argument(
        "--plant",
        dest="plant_file",
        metavar="FILE",
        help="start from this plant file (jaxcart fit --out, diagnose): its effects and values",
    )
    p.add_argument(
        "--json",
        dest="json_out",
        metavar="OUT",
        help="write the report as JSON (or, for a name ending in .mat, as a MATLAB struct)",
    )
    p.add_argument("--plot", metavar="PNG", help="overlay plot of recordings and model")

    add_format_option(p)
    p.add_argument(
        "--out",
        metavar="PLANT.toml",
        help="write the fitted plant as a plant file (for simulate, tune, grid, lab --plant)",
    )
    p.add_argument("--classic", action="store_true", help="add the lab's classic estimates")
    p.add_argument(
        "--cross",
        action="store_true",
        help="fit each recording alone and predict the others with it",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")

    add_helpers_option(p)
    # With --cross, each process fits its share of the recordings alone; process 0 alone runs
    # the joint fit and writes the outputs.
    add_cluster_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    # lazy: imports jax and the fit, 0.5 s at start-up (python -X importtime)
    from jaxcart import parallel
    from tuning.estimation.fit import parse_params

    params = parse_params(args.params)
    if not params:
        raise UserError("--params: name at least one parameter, e.g. --params B_eq,f_c")
    if args.cross and len(args.experiments) < 2:
        raise UserError("--cross needs at least two recordings")
    if args.out and not str(args.out).lower().endswith(".toml"):
        raise UserError(f"--out {args.out}: a plant file is TOML; give a name ending in .toml")
    # jax.distributed joins before any computation starts a backend.
    settings = parallel.cluster_settings(args.coordinator, args.num_processes, args.process_id)
    # Process 0's outputs are checked before it joins where its index is known: a bad path
    # fails at once instead of leaving the other processes waiting for it.
    checked = settings is None or (settings != "auto" and settings[2] == 0)
    if checked:
        check_outputs(args)
    share = None
    if parallel.init_distributed(settings):
        # lazy: imports jax, 0.3 s at start-up (python -X importtime)
        from tuning.distributed import Exchange

        share = Exchange()

    with helpers(args, distributed=share is not None) as pool:
        return _run(args, params, share, checked, pool)


def _run(args, params, share, checked, pool) -> int:
    """Fit (and cross-predict), print and write; share: the distributed run's exchange (else
    None); checked: process 0's outputs were checked before it joined; pool: the command's
    helper processes, which make the fits' exact runs several at a time."""
    # lazy: imports jax and the fit, 0.5 s at start-up (python -X importtime)
    from jaxcart import parallel
    from jaxcart.files import read_experiment
    from tuning.estimation.fit import fit

    me = parallel.process_index()
    progress = not args.quiet and me == 0
    recordings, result, failure, report = [], None, None, None
    try:
        if me == 0 and not checked:
            check_outputs(args)
        recordings = [read_experiment(path) for path in args.experiments]
        if me == 0:
            _warn_if_long(recordings)
            initial = _initial(args.plant_file)
            # The joint fit is one problem: process 0 alone computes it (the others fit their
            # rows of --cross meanwhile) and reports it.
            result = fit(
                recordings,
                params,
                per_recording=args.per_recording,
                initial=initial,
                progress=progress,
                executor=pool,
            )
        if result is not None:
            print(format_result(result))
            report = result.to_json()
            if args.classic:
                classic = classic_estimates(recordings, result)
                print(format_classic(classic))
                report["classic"] = [{"recording": n, **c.to_json()} for n, c in classic]
    except Exception as exc:
        if share is None:
            raise
        # Sent in the exchange (tuning.distributed.Exchange.allgather: a UserError as it is, any
        # other as one line naming its type and process) and raised on every process.
        failure = exc
    cross = None
    if args.cross:
        cross = cross_fit.cross_table(
            recordings, params, progress=progress, processes=share, failure=failure, executor=pool
        )
    elif share is not None:
        cross_fit.share(share, {}, failure)
    if share is not None and not share.finish():
        what = "results sent to process 0" if args.cross else "process 0 fits and reports"
        print(f"process {me} of {share.count}: done, {what}")
        return 0
    if cross is not None:
        print(format_cross(cross))
        if share is not None:
            print(f"  (each recording fitted by one of {share.count} processes)")
        report["cross_prediction"] = cross

    with all_or_none(args.json_out, args.out, args.plot):  # all written, or none left
        _write_outputs(args, report, result)
    return edge_status(result)


def edge_status(result) -> int:
    """1 where a fitted parameter (the command's headline) sits on an edge of its allowed
    range, said in one line last, else 0."""
    edges = [n for n, e in result.params.items() if e.edge is not None] if result else []
    if not edges:
        return 0
    print(
        f"fit: {', '.join(edges)} at the edge of the allowed range: no estimate (exit status 1; "
        "see the warning above)",
        file=sys.stderr,
    )
    return 1


def _write_outputs(args, report, result) -> None:
    # lazy: imports jax and the fit, 0.5 s at start-up (python -X importtime)
    from tuning.estimation.fit import plot_fit, write_fitted_plant

    if args.json_out and str(args.json_out).lower().endswith(".mat"):
        # lazy: imports jax, 0.3 s at start-up (python -X importtime)
        from jaxcart.matfile import write_mat_report

        write_mat_report(args.json_out, report, name="fit", force=args.force)
        print(f"report: {args.json_out}")
    elif args.json_out:
        write_json(args.json_out, report, force=args.force)
        print(f"report: {args.json_out}")
    if args.out:
        write_fitted_plant(args.out, result, sources=args.experiments, force=args.force)
        print(f"fitted plant: {args.out}")
    if args.plot:
        plot_fit(result, args.plot)
        print(f"plot: {args.plot}")


def _initial(plant_file) -> dict:
    """Start (and fixed) values of --plant, {name: value} [SI]; {} without it."""
    if not plant_file:
        return {}
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.plantsource import load_plant
    from jaxcart.plantspec import plant_values

    plant = load_plant(plant_file)
    # B_eq too where the file leaves the handout's (plant_values leaves those out): a value
    # given, not one to read off the recordings.
    return {"B_eq": float(plant.B_eq), **plant_values(plant)}


#: Samples beyond which a fit is said to be long before it starts (each of its ~100
#: evaluations simulates every sample; the lab's recordings have 2,000-20,000).
LONG_FIT_SAMPLES = 300_000


def _warn_if_long(recordings) -> None:
    n = sum(int(r.n_samples) for r in recordings)
    if n > LONG_FIT_SAMPLES:
        print(
            f"jaxcart fit: warning: {n:,} samples; each of the fit's ~100 evaluations "
            "simulates all of them, so this can take many minutes. The parameters live in a "
            "few seconds of coast or step response: crop the recording to those.",
            file=sys.stderr,
        )


def check_outputs(args) -> None:
    """Every output path writable (not under a file, not in a read-only folder, not an
    existing file without --force), checked before the fit computes anything; --plot takes
    the suffix of --format."""
    if args.format and not args.plot:
        raise UserError(f"--format {args.format}: name the figure with --plot (e.g. fit.pdf)")
    if args.plot:
        args.plot = str(figure_name(args.plot, args.format))

    for option, path, suffixes in (
        ("--json", args.json_out, None),
        ("--plot", args.plot, PLOT_SUFFIXES),
        ("--out", args.out, (".toml",)),
    ):
        if path:
            check_writable(path, suffixes=suffixes, option=option, force=args.force)


def _mm(x) -> str:
    return "-" if x is None else f"{x * 1e3:.4g}"


def format_result(result) -> str:
    """The parameter table and the RMS errors, as printed by the command."""
    # lazy: imports jax and the fit, 0.5 s at start-up (python -X importtime)
    from jaxcart.plantspec import describe_plant
    from tuning.estimation.fit import unit_of

    lines = ["recordings:"]
    for s in result.segments:
        what = "coasting part" if s.kind == "tap" else "whole run"
        lines.append(
            f"  {s.name}: {s.kind}, {what} {s.time[0]:.3f} to {s.time[-1]:.3f} s "
            f"({s.measured.size} samples)"
        )
        lines.append(f"    model fitted: {describe_plant(s.plant)}")
    lines.append(f"{'parameter':<14}{'value':>14}{'stderr':>12}{'naive':>12}  unit")
    names = [s.name for s in result.segments]
    for key, e in result.params.items():
        base, _, k = key.partition("@")
        unit = unit_of(base)
        name = f"{base} ({names[int(k)]})" if k else key
        if not e.identifiable:  # the note says why, and where the value held comes from
            lines.append(f"{name:<14}{e.note}")
            continue
        edge = f"  AT THE {e.edge[0].upper()} EDGE of its range: no estimate" if e.edge else ""
        lines.append(
            f"{name:<14}{e.value:>14.6g}{e.stderr:>12.3g}{e.stderr_naive:>12.3g}  {unit}{edge}"
        )
    for s in result.segments:
        for v, e in s.nuisance.items():
            unit = "m/s" if v == "yd0" else "m"
            lines.append(f"{s.name + ':' + v:<14}{e.value:>14.6g}{e.stderr:>12.3g}{'':>12}  {unit}")
    lines.append(f"RMS position error [mm]{'before':>12}{'after':>12}")
    lines.append(f"  {'smooth model':<21}{_mm(result.rms_before):>12}{_mm(result.rms_after):>12}")
    lines.append(
        f"  {'exact simulator':<21}{_mm(result.rms_before_exact):>12}"
        f"{_mm(result.rms_after_exact):>12}"
    )
    if len(result.segments) > 1:
        for s in result.segments:
            lines.append(
                f"  {s.name + ' (exact)':<21}{_mm(s.rms_before_exact):>12}"
                f"{_mm(s.rms_after_exact):>12}"
            )
    for (a, b), c in result.correlation.items():
        lines.append(f"correlation {a}, {b}: {c:+.3f}")
    for text in result.warnings:
        lines.append(f"warning: {text}")
    lines.append(f"fitted in {result.seconds:.1f} s")
    return "\n".join(lines)


def classic_estimates(recordings, result=None) -> list:
    """[(recording name, ClassicEstimate)] of the methods that apply to each recording."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from tuning.estimation import classic
    from tuning.estimation.engine.segments import recording_name

    out = []
    for rec in recordings:
        name = recording_name(rec)
        try:
            if rec.kind == "tap":
                out.append((name, classic.loglinear_beq(rec)))
            elif rec.kind == "open_loop":
                out.append((name, classic.ramp_breakaway_fc(rec)))
            elif rec.controller is not None and rec.controller.ki == 0:
                out.append((name, classic.pcontrol_fc_bounds(rec)))
        except UserError as exc:
            print(f"classic ({name}): skipped: {exc}", file=sys.stderr)
    return out


def format_classic(classic) -> str:
    # lazy: imports jax and the fit, 0.5 s at start-up (python -X importtime)
    from tuning.estimation.fit import unit_of

    lines = ["classic estimates:"]
    for name, c in classic:
        unit = unit_of(c.name)
        if c.value is not None:
            se = f" +/- {c.stderr:.3g}" if c.stderr is not None else ""
            text = f"{c.name} = {c.value:.4g}{se} {unit}"
        else:
            upper = f" < {c.upper:.4g}" if c.upper is not None else ""
            text = f"{c.lower:.4g} <= {c.name}{upper} {unit}"
        lines.append(f"  {name}: {text}   [{c.method}]")
    return "\n".join(lines)


def format_cross(rows) -> str:
    lines = ["cross-prediction (exact simulator RMS [mm]; the start state of a tap refitted):"]
    for r in rows:
        vals = ", ".join(
            f"{k} = {v:.4g}" + (" (held)" if k in r["held"] else "") for k, v in r["values"].items()
        )
        rms = r["rms"] if r["rms"] is not None else r["rms_smooth"]
        note = " (own fit)" if r["fitted_on"] == r["predicting"] else ""
        what = "failed" if rms is None else f"{_mm(rms)} mm{note}"
        lines.append(f"  {r['fitted_on']} -> {r['predicting']}: {what}   [{vals}]")
    return "\n".join(lines)
