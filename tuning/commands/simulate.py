"""``jaxcart simulate``: simulate an experiment file (or the lab's design problem) and write the
result as an experiment file, so that the output of one command is the input of the next.

    jaxcart simulate                               # lab default: step 0.5 m, kp 40, ki 5, kd 5
    jaxcart simulate p50.toml --out p50-sim.csv --plot p50-sim.png
    jaxcart simulate run.toml --kp 60 --ki 2 --kd 6 --smooth

The exact simulator is the default: it is the one a recording is compared with (the Coulomb
dead band of a P loop, a stick-slip, a hard clip). ``--smooth`` runs the smoothed simulator the
tuner and the fits differentiate, with its widths stated, and says that a comparison with data
is then the smoothed model's.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

import jaxcart as jc
from hw.atomicio import all_or_none
from hw.control_law import setting_problem
from hw.expfile import SIMULATED_BY
from jaxcart import plots
from jaxcart.errors import SimulationDiverged, UserError
from jaxcart.outputs import OUT_DIR, check_writable, free_names
from jaxcart.plots import add_format_option, figure_name
from tuning.commands.options import NOT_RISEN, timed

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).


#: The lab's design problem (docs/design.md, "The design problem"): step 0.5 m, handout plant,
#: 6 V, the handout's gains.
DEFAULT_STEP = 0.5
DEFAULT_GAINS = {"kp": 40.0, "ki": 5.0, "kd": 5.0}
DEFAULT_V_LIMIT = 6.0
DEFAULT_HORIZON = 3.0
GAIN_OPTIONS = ("kp", "ki", "kd", "tau", "v_limit")
#: Figure formats of --plot (matplotlib's, by suffix).
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
#: The .mat layouts of ``--mat-layout`` (jaxcart.matfile.LAYOUTS; not imported here: the
#: parser must not import jaxcart).
MAT_LAYOUTS = ("structure-with-time", "structure", "array", "vector")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate an experiment file (default: the lab's PID design problem)",
        description=(
            "Simulate EXPERIMENT.toml (or, without it, the lab's design problem: step 0.5 m, "
            "kp=40, ki=5, kd=5, 6 V limit, handout plant, 3 s) on the exact simulator (--smooth: "
            "the smoothed one) and write the run as an "
            "experiment file (CSV or MATLAB .mat, + TOML), with a figure. Without --out, files "
            "go to ./jaxcart-out/ under names that never overwrite; a recording whose data are "
            ".mat files is written back as .mat in the Simulink layout it came in."
        ),
    )
    p.add_argument(
        "experiment",
        nargs="?",
        metavar="EXPERIMENT.toml",
        help="experiment file to simulate (default: the lab's design problem)",
    )
    p.add_argument(
        "--out",
        metavar="RUN.csv|RUN.mat",
        help="write RUN.csv (or RUN.mat, one variable per signal) and RUN.toml (default: "
        "./jaxcart-out/run.csv, run-2.csv...)",
    )
    p.add_argument(
        "--mat-layout",
        choices=MAT_LAYOUTS,
        help="layout of each signal in a .mat output (default: as the recording's .mat came "
        "in, else structure-with-time, the Simulink scope's 'Structure With Time')",
    )
    p.add_argument("--plot", metavar="RUN.png", help="write the figure here")

    add_format_option(p)
    which = p.add_mutually_exclusive_group()
    which.add_argument(
        "--exact",
        action="store_true",
        help="the exact (nonsmooth, event-exact) simulator: the default, the one to compare "
        "with a recording",
    )
    which.add_argument(
        "--smooth",
        action="store_true",
        help="the smoothed simulator the tuner and the fits differentiate (its widths are "
        "printed; its friction and clip corners shift a dead band or a stick-slip)",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.add_argument(
        "--plant",
        metavar="PLANT.toml",
        help="simulate this plant (a plant file from fit or diagnose, or an experiment file "
        "whose [plant] applies) instead of the experiment's",
    )
    p.add_argument(
        "--horizon",
        type=float,
        metavar="S",
        help="simulated time [s] (default: the recording's length, or 3 s)",
    )
    p.add_argument("--kp", type=float, help="proportional gain [V/m] (overrides the file)")
    p.add_argument("--ki", type=float, help="integral gain [V/(m s)]")
    p.add_argument("--kd", type=float, help="derivative gain [V s/m]")
    p.add_argument("--tau", type=float, help="derivative filter time constant [s]")
    p.add_argument(
        "--v-limit", dest="v_limit", type=float, help="software voltage limit [V] (inf for none)"
    )
    p.set_defaults(func=run)


def run(args) -> int:
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart import plausibility
    from jaxcart.files import read_experiment

    recording = read_experiment(args.experiment) if args.experiment else None
    # Outputs first: a bad path fails now, not after the run.
    csv_path, toml_path, png_path = _outputs(args, recording)
    if recording is not None:
        source = str(recording.path)
        plant, controller = recording.plant(), recording.controller
        _check_horizon(args.horizon, recording.sample_time, recording.n_samples)
        experiment = (
            recording.experiment_for(args.horizon)
            if args.horizon is not None
            else recording.experiment
        )
        released = _released(recording) if args.horizon is None else None
        if released is not None:
            experiment = released.experiment
        overrides = recording.plant_overrides
    else:
        released = None
        source = "the default experiment"
        horizon = DEFAULT_HORIZON if args.horizon is None else args.horizon
        if not (math.isfinite(horizon) and horizon > 0):
            raise UserError(f"--horizon {horizon!r}: give a positive number of seconds")
        plant = jc.handout_plant()
        controller = jc.PID(v_limit=DEFAULT_V_LIMIT, **DEFAULT_GAINS)
        _check_horizon(horizon, 0.001, None)
        experiment = jc.step(DEFAULT_STEP, horizon=horizon)
        overrides = {}
    if args.plant:
        # lazy: imports jax, 0.3 s at start-up (python -X importtime)
        from jaxcart.plantsource import load_plant
        from jaxcart.plantspec import plant_values

        chosen = load_plant(args.plant)
        plant = dataclasses.replace(chosen, motor_connected=plant.motor_connected)
        overrides = plant_values(plant)
    controller = _with_options(args, controller, experiment, source)
    checked = recording is not None and not args.plant and controller == recording.controller
    if controller is not None and not checked:
        # Before the run: an unstable or implausible loop is said, not discovered in the output
        # (a recording's own controller was checked when it was read).
        for message in plausibility.check_controller(controller, plant, where="controller"):
            plausibility.warn(message)

    response = _simulate(_solver(args.smooth, experiment), plant, controller, experiment)
    if bool(np.asarray(response.diverged)):
        raise SimulationDiverged(
            f"simulation of {source} diverged (|y| > 1 km or not finite) with "
            f"{_gains(controller) if controller else 'no controller'}; lower the gains, set a "
            f"voltage limit (--v-limit 6) or check [plant]"
        )
    if recording is not None:
        first = 0 if released is None else released.start
        # Keep the recording's clock so that the two files line up sample by sample.
        response = dataclasses.replace(
            response, time=np.asarray(response.time) + recording.time[first]
        )

    method = "smooth" if args.smooth else "exact"
    written = dict(
        controller=controller if experiment.kind == "closed_loop" else None,
        plant_overrides=overrides,
        description=f"{SIMULATED_BY} ({method} simulator) of {source}",
        force=args.force,
    )

    with all_or_none(csv_path, toml_path, png_path):  # a failed figure leaves no data either
        if csv_path.suffix.lower() == ".mat":
            # lazy: imports jax, 0.3 s at start-up (python -X importtime)
            from jaxcart.matfile import source_layout, write_mat_experiment

            layout = source_layout(recording) if recording is not None else None
            write_mat_experiment(
                csv_path, response, layout=args.mat_layout, source=layout, **written
            )
        else:
            # lazy: imports jax, 0.3 s at start-up (python -X importtime)
            from jaxcart.files import write_experiment

            write_experiment(toml_path, response, **written)
        if png_path is not None:
            _plot(png_path, response, recording, controller, plant, source, method)
    _summary(
        source,
        experiment,
        method,
        controller,
        plant,
        response,
        recording,
        (csv_path, toml_path, png_path),
        released,
    )
    return 0


# ---------------------------------------------------------------- pieces


def _with_options(args, controller, experiment, source):
    """The controller with the command-line gains applied."""
    given = {k: getattr(args, k) for k in GAIN_OPTIONS if getattr(args, k) is not None}
    if experiment.kind != "closed_loop":
        if given:
            names = ", ".join("--" + k.replace("_", "-") for k in given)
            raise UserError(
                f"{names}: {source} is a {experiment.kind} experiment, which has no "
                f"controller; drop the option(s)"
            )
        return None
    if controller is None and not given:
        raise UserError(
            f"{source} has no [controller]; add one or give the gains with --kp/--ki/--kd"
        )

    base = controller or jc.PID(sample_time=experiment.sample_time)
    for name, value in given.items():
        # The one rule of a PID setting; a negative gain is allowed here as in the experiment
        # file that simulate writes (a what-if of a sign error, flagged unstable before the run).
        problem = setting_problem(name, value, allow_negative_gains=True)
        if problem:
            raise UserError(f"--{name.replace('_', '-')} {value!r}: {name} = {problem}")
    return dataclasses.replace(base, **given)


def _outputs(args, recording):
    """(data: .csv or .mat, toml, png or None), refusing existing files unless --force, before
    simulating."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.files import experiment_paths
    from jaxcart.matfile import mat_paths

    if args.out:
        out = Path(args.out)
        if out.suffix.lower() not in (".csv", ".toml", ".mat"):
            raise UserError(
                f"--out {args.out}: give a name ending in .csv or .mat (the TOML is written "
                "beside it)"
            )
        if out.suffix.lower() == ".mat":
            toml_path, csv_path = mat_paths(out)
        else:
            toml_path, csv_path = experiment_paths(out)
        png_path = figure_name(args.plot, args.format) if args.plot else None
        if png_path is None and args.format:  # --format asks for the figure, beside the data
            png_path = csv_path.with_suffix("." + args.format)
    else:
        stem = "run" if recording is None else f"{recording.path.stem}-sim"
        data = ".mat" if args.mat_layout or _mat_data(recording) else ".csv"
        figure = "." + (args.format or "png")
        csv_path, toml_path, auto_png = free_names(OUT_DIR, stem, (data, ".toml", figure))
        png_path = figure_name(args.plot, args.format) if args.plot else auto_png
    if args.mat_layout and csv_path.suffix.lower() != ".mat":
        raise UserError(f"--mat-layout {args.mat_layout}: the output {csv_path} is not .mat")
    option = "--out" if args.out else None
    check_writable(csv_path, suffixes=(".csv", ".mat"), option=option, force=args.force)
    check_writable(toml_path, suffixes=(".toml",), option=option, force=args.force)
    if png_path is not None:
        check_writable(
            png_path,
            suffixes=PLOT_SUFFIXES,
            option="--plot" if args.plot else None,
            force=args.force,
        )
    return csv_path, toml_path, png_path


class _Released(NamedTuple):
    """A tap simulated from where the hand let go: its first sample in the recording and the
    experiment from there to the recording's end."""

    start: int
    experiment: object


def _released(recording) -> _Released | None:
    """A tap recording without its own ``initial_velocity``, from where the hand let go (the
    start of the coasting part the fit uses, :func:`tuning.estimation.engine.segments.prepare`,
    with its position and velocity read from the recording) to its end: the push before it
    is a hand's, not the model's. None for any other recording."""
    if recording.kind != "tap" or "initial_velocity" in recording.meta:
        return None
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from tuning.estimation.engine.segments import prepare

    seg = prepare(recording)
    signal = np.asarray(recording.experiment.signal)[seg.start :]
    return _Released(
        seg.start,
        dataclasses.replace(
            recording.experiment, signal=signal, y0=seg.experiment.y0, yd0=seg.experiment.yd0
        ),
    )


def _check_horizon(horizon, sample_time, n_recorded):
    """Refuse, before any array is built, a run that would not fit in memory."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart import chunked_sim

    if horizon is not None and not (math.isfinite(horizon) and horizon > 0):
        return  # the experiment's own check names the bad value
    n = n_recorded if horizon is None else int(round(horizon / sample_time)) + 1
    what = f"--horizon {horizon:g}" if horizon is not None else "the recording"
    chunked_sim.check_size(n, sample_time, what)


def _mat_data(recording) -> bool:
    """Whether the recording's data came from MATLAB .mat files (then the run goes back so)."""
    data = recording.meta.get("data") if recording is not None else None
    return isinstance(data, dict) and any(
        str(source).rpartition(":")[0].lower().endswith(".mat") for source in data.values()
    )


def _solver(smooth: bool, experiment):
    """The simulator the options choose, as a value (jaxcart.simulate's solver): the exact one,
    or with --smooth the smooth one, in chunks with progress for a long run."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart import chunked_sim

    if not smooth:
        return jc.Exact()
    if experiment.n_samples > chunked_sim.LONG_SAMPLES:
        columns = {"closed_loop": 5, "open_loop": 3, "tap": 2}[experiment.kind]
        return jc.Chunked(n_columns=columns)
    return jc.Smooth()


def _simulate(solver, plant, controller, experiment):
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    import jax

    from jaxcart import chunked_sim

    pid = controller if controller is not None else jc.PID(sample_time=experiment.sample_time)
    if isinstance(solver, jc.Smooth):
        return jax.jit(functools.partial(jc.simulate, solver=solver))(plant, pid, experiment)
    if isinstance(solver, jc.Exact) and experiment.n_samples > chunked_sim.EXACT_PROBE:
        columns = {"closed_loop": 5, "open_loop": 3, "tap": 2}[experiment.kind]
        seconds = chunked_sim.estimate_exact(plant, pid, experiment)
        chunked_sim.announce(seconds, experiment.n_samples, columns, experiment.sample_time)
    return jc.simulate(plant, pid, experiment, solver=solver)


def _widths() -> str:
    """The smooth simulator's widths, as the summary states them."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.smoothing import Smoothing

    w = Smoothing()
    return (
        f" (smoothing widths: voltage {w.voltage:g} V, velocity {w.velocity:g} m/s, position "
        f"{w.position:g} m)"
    )


def _gains(pid) -> str:
    text = f"kp={float(pid.kp):g}, ki={float(pid.ki):g}, kd={float(pid.kd):g}"
    return text + f", tau={float(pid.tau):g} s, v_limit={float(pid.v_limit):g} V"


def _voltage_limit(plant, controller) -> float:
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.params import voltage_limit

    return float(voltage_limit(plant, controller))


def _plot(path, response, recording, controller, plant, source, method):
    runs = []
    if recording is not None:
        runs.append(plots.run_from_recording(recording))
    if response.kind == "closed_loop":
        runs.append(plots.reference_run(response.time, response.reference))
    runs.append(plots.run_from_response(response, f"simulated ({method})"))
    runs = [_thinned(run) for run in runs]  # a 1e7-sample curve: minutes in matplotlib
    title = Path(source).name if recording is not None else "default: step 0.5 m"
    if controller is not None:
        title += f" | {_gains(controller)}"
    plots.plot_runs(
        runs,
        title=title,
        path=path,
        voltage=response.kind != "tap",
        v_limit=_voltage_limit(plant, controller),
        zoom=response.kind == "closed_loop",  # the steady-state error in mm
    )


def _thinned(run):
    """The run with at most about chunked_sim.PLOT_POINTS samples, each block's extremes kept."""
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.chunked_sim import thin_indices

    keep = thin_indices(len(run.time), run.position, run.voltage)
    if keep.size == len(run.time):
        return run
    voltage = None if run.voltage is None else np.asarray(run.voltage)[keep]
    return dataclasses.replace(
        run,
        time=np.asarray(run.time)[keep],
        position=np.asarray(run.position)[keep],
        voltage=voltage,
    )


def _is_step(response) -> bool:
    r = np.asarray(response.reference)
    return (
        response.kind == "closed_loop"
        and bool(np.all(r == r[-1]))
        and r[-1] != np.asarray(response.position)[0]
    )


def _metrics_line(info) -> str:
    return (
        f"{timed('rise', info.rise_time, NOT_RISEN)}, {timed('settling', info.settling_time)}, "
        f"overshoot {info.overshoot:.2f} %, steady-state error "
        f"{1e3 * info.steady_state_error:.2f} mm, peak {info.peak_voltage:.2f} V"
    )


def _summary(
    source, experiment, method, controller, plant, response, recording, paths, released=None
):
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.plantspec import describe_plant

    n = experiment.n_samples
    print(
        f"simulated {source}: {experiment.kind}, {n} samples ({(n - 1) * experiment.sample_time:g}"
        f" s), {method} simulator{_widths() if method == 'smooth' else ''}"
    )
    print(f"  plant: {describe_plant(plant)}")
    if controller is not None:
        print(
            f"  controller: {_gains(controller)}, derivative on {controller.derivative_on}, "
            f"anti-windup {controller.anti_windup}"
        )
    if _is_step(response):
        limit = _voltage_limit(plant, controller)
        print(f"  simulated: {_metrics_line(jc.step_info(response, v_limit=limit))}")
        if recording is not None and recording.reference is not None:
            measured = recording.as_response()
            print(f"  recorded:  {_metrics_line(jc.step_info(measured, v_limit=limit))}")
    if released is not None:
        print(
            f"  tap from where the hand let go, t = {recording.time[released.start]:.3f} s: "
            f"y0 = {experiment.y0:.4g} m, initial velocity {float(experiment.yd0):.4g} m/s "
            "(read from the recording; the push before it is not simulated)"
        )
    elif experiment.kind == "tap":
        print(
            f"  tap from y0 = {experiment.y0:g} m with initial_velocity = "
            f"{float(experiment.yd0):g} m/s (the file's initial_velocity)"
        )
    if recording is not None:
        first = 0 if released is None else released.start
        k = min(recording.n_samples - first, n)
        diff = np.asarray(response.position)[:k] - recording.position[first : first + k]
        print(
            f"  position minus recording ({method} simulator): rms "
            f"{1e3 * np.sqrt(np.mean(diff**2)):.2f} mm, max |.| {1e3 * np.abs(diff).max():.2f} mm "
            f"over {k} samples"
        )
        if method == "smooth":
            print(
                "  note: this compares the smoothed model with data: its friction and clip "
                "corners shift a dead band or a stick-slip; the exact simulator (without "
                "--smooth) is the model to compare with a recording"
            )
    # lazy: imports jax, 0.3 s at start-up (python -X importtime)
    from jaxcart.plausibility import check_track

    for message in check_track(response, "warning"):  # in the summary, beside the metrics
        print(f"  {message}")
    print("  wrote " + ", ".join(str(p) for p in paths if p is not None))
    sys.stdout.flush()
