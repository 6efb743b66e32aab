"""``jaxcart diagnose``: where recordings and model part, which physics was left out, the model
with it, and the fit improving.

    jaxcart diagnose run.toml [more.toml ...] [--plant START.toml] [--json OUT] [--out DIR]
    jaxcart diagnose --suite          # the concealed-effect suite, its score table
    jaxcart diagnose run.toml --coordinator node0:12345 --num-processes 2 --process-id 0
"""

from __future__ import annotations

from pathlib import Path

from jaxcart.errors import UserError
from jaxcart.outputs import check_writable
from jaxcart.plots import add_format_option
from tuning.commands.options import add_cluster_options, add_helpers_option, helpers

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="locate where recordings and the model part, name and model the left-out physics",
        description="Baseline (the handout's model, B_eq fitted) on the exact simulator; "
        "windows where the residual has structure beyond the encoder's quantization; candidate "
        "structures from the effects library fitted in batches through the smoothed simulator, "
        "re-checked on the exact one and chosen by an information criterion; the corrected "
        "plant, a report, a figure. Several recordings of one cart are diagnosed jointly.",
    )
    p.add_argument("experiments", nargs="*", metavar="EXPERIMENT.toml", help="recordings")
    p.add_argument("--plant", dest="plant_file", metavar="START.toml", help="start plant file")
    p.add_argument("--json", dest="json_out", metavar="OUT", help="write the diagnosis as JSON")
    p.add_argument("--out", metavar="DIR", help="report folder (default ./jaxcart-out/diagnose-N)")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument(
        "--curve",
        action="store_true",
        help="where nothing named explains the recordings, read friction as a curve of the "
        "speed (each direction) and, where they cover 0.4 m of the track, of the position "
        "(each named where it predicts the recordings held out better)",
    )

    add_format_option(p)
    p.add_argument("--suite", action="store_true", help="run the concealed-effect suite")
    p.add_argument("--fast", action="store_true", help="with --suite: the CI subset only")

    add_helpers_option(p)
    add_cluster_options(p)
    p.set_defaults(func=run)


def _default_out() -> Path:
    base = Path("jaxcart-out")
    k = 1
    while (base / f"diagnose-{k}").exists():
        k += 1
    return base / f"diagnose-{k}"


def _check_outputs(args) -> Path:
    """The report folder, its files and --json checked writable (and absent unless --force)."""
    out = Path(args.out) if args.out else _default_out()

    for p in (out / "report.md", out / "corrected_plant.toml", args.json_out):
        if p and Path(p).exists() and not args.force:
            raise UserError(f"{p} exists; choose another --out/--json or pass --force")
    # Before the minutes of diagnosis: a folder under a file or a read-only place fails now.
    check_writable(out / "report.md", option="--out", force=True)
    if args.json_out:
        check_writable(args.json_out, option="--json", force=True)
    return out


def run(args) -> int:
    if args.suite:
        # lazy: imports jax and the diagnosis, 0.6 s at start-up (python -X importtime)
        from tuning.estimation.diagnose.suite import main as suite_main

        return suite_main(["--fast"] if args.fast else [])
    if not args.experiments:
        raise UserError("give at least one experiment file (EXPERIMENT.toml), or --suite")
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart import parallel

    # jax.distributed joins before any computation starts a backend.
    settings = parallel.cluster_settings(args.coordinator, args.num_processes, args.process_id)
    # Process 0's outputs are checked before it joins where its index is known: a bad path
    # fails at once instead of leaving the other processes waiting for it.
    checked = settings is None or (settings != "auto" and settings[2] == 0)
    out = _check_outputs(args) if checked else None

    if not parallel.init_distributed(settings):
        with helpers(args) as pool:
            return _run(args, None, out, pool)
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from tuning.distributed import Exchange

    share = Exchange()
    # An error one process meets from here on (a recording only some hosts have, a failure
    # mid-run) is raised on every process, none waiting for a partner that has stopped.
    with share.carry():
        return _run(args, share, out, helpers(args, distributed=True))


def _run(args, share, out, pool) -> int:
    """Diagnose and write the outputs. share: the :class:`tuning.distributed.Exchange` of a
    distributed run (else None); out: the report folder, where checked before joining; pool:
    the command's helper processes for the exact runs."""
    # lazy: imports jax and the diagnosis, 0.4 s at start-up (python -X importtime)
    from jaxcart import parallel
    from jaxcart.files import read_experiment
    from tuning.estimation.diagnose import diagnose, write_outputs

    me = parallel.process_index()
    if me == 0 and out is None:
        out = _check_outputs(args)
    recordings = [read_experiment(path) for path in args.experiments]
    start = None
    if args.plant_file:
        # lazy: imports jax, 0.3 s at start-up (python -X importtime)
        from jaxcart.plantsource import load_plant

        start = load_plant(args.plant_file)
    if share is not None:
        share.sync()  # every process has its inputs: an error reading them stops all now
    progress = not args.quiet and me == 0
    d = diagnose(
        recordings,
        start=start,
        progress=progress,
        processes=share,
        executor=pool,
        curve=args.curve,
    )
    if share is not None and not share.finish():
        print(f"process {me} of {share.count}: done, results sent to process 0")
        return 0 if d.status == "diagnosed" else 1
    written = write_outputs(
        d, out, json_path=args.json_out, force=args.force, fmt=args.format or "png"
    )
    print(d.verdict)
    if d.status == "diagnosed":
        print(
            f"RMS (exact simulator): {d.rms_before * 1e3:.4f} mm before, "
            f"{d.rms_after * 1e3:.4f} mm after (encoder floor {d.floor * 1e3:.4f} mm)"
        )
        for n, p in d.parameters.items():
            print(f"  {n} = {p['value']:.6g} +/- {p['stderr']:.2g} {p['unit']}")
    for what, path in written.items():
        print(f"{what}: {path}")
    return 0 if d.status == "diagnosed" else 1
