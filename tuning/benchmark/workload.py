"""Benchmark of workload W1 (docs/design.md, "Benchmark workload W1"): jaxcart beside its
peers, measured in one process.

W1 is the lab's design problem as a batch job: the discrete PID (derivative on error, tau =
0.01 s, software limit 6 V) drives the handout's cart (B_eq = 5.4 kg/s, amplifier saturation
6 V) through a 0.5 m step for 3 s at Ts = 1 ms (3001 samples), for a batch of gain triples
(kp, kd, ki) drawn from a fixed seed. One simulation is the closed loop plus its step metrics.

Five implementations of that same loop are timed, and checked against each other first:

    jaxcart            step_metrics_batch, float32 (and float64), sharded over every device
    c-kernel           the ceiling: a minimal C kernel of exactly W1 (ckernel.py), built
                       with the system's C compiler, vectorized across runs, one thread
    python-control     a discrete-time nlsys (dt = Ts) + input_output_response, one run at a time
    scipy              solve_ivp over each hold interval, the PID updated at each sample
    numpy-vectorized   the recursion over a batch in numpy, time loop in Python, metrics streamed

The peers (tuning/benchmark/peers.py) share nothing with jaxcart's simulator but the control
law (hw.control_law, the code the hardware runs): the plant step is the exact zero-order hold
computed with scipy.linalg.expm (python-control, numpy) or integrated by solve_ivp, and the
metrics are computed in numpy. The reference is float64 ``jaxcart.simulate`` with EXACT_FORMS (hard
clips); a float64 peer further than ``TOLERANCE`` [m] from it in position (or a sample off in
a metric) raises :class:`PeerDisagreement` and no figure is reported.

jaxcart and the C kernel are also compared per CPU-second (process CPU time for jaxcart, all
its threads; the calling thread's CPU time for the single-threaded kernel): the jaxcart rows'
``ceiling_ratio`` is their rate over the kernel's in the same precision.

>>> result = run_bench(quick=True)              # doctest: +SKIP
>>> print(format_table(result))                 # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import sys
import time
from collections.abc import Callable

import control
import jax
import jax.numpy as jnp
import numpy as np
import scipy

import jaxcart
from hw.control_law import PID
from jaxcart import parallel
from jaxcart.accumulators import accumulate, value_and_jacfwd_rows
from jaxcart.batch_metrics import (
    COMPILER_OPTIONS,
    WIDE_CHUNK,
    default_chunk,
    loops_whole,
    step_metrics_batch,
)
from jaxcart.parallel import sharded_map
from jaxcart.params import voltage_limit
from jaxcart.smoothing import smooth_relu
from tuning.benchmark import ckernel
from tuning.benchmark.peers import numpy_batch, python_control_run, scipy_run, trace_metrics

#: Workload W1 (docs/design.md, "Benchmark workload W1"): the step [m], horizon [s], sample
#: time [s], limits [V], filter [s].
STEP = 0.5
HORIZON = 3.0
SAMPLE_TIME = 1e-3
V_LIMIT = 6.0
TAU = 0.01
#: Ranges of the gains: kp [V/m], kd [V s/m], ki [V/(m s)]; and the seed that draws them.
GAIN_RANGES = {"kp": (10.0, 120.0), "kd": (0.0, 12.0), "ki": (0.0, 30.0)}
SEED = 364
#: The default ranges of ``jaxcart grid`` (``DEFAULT_RANGES`` of tuning/commands/grid.py, as
#: numbers: a test keeps the two equal).
GRID_RANGES = {"kp": (10.0, 150.0), "kd": (0.0, 15.0), "ki": (0.0, 30.0)}
#: Largest position difference [m] a float64 peer may show against float64 jaxcart.
TOLERANCE = 1e-6
METRICS = (
    "rise_time",
    "settling_time",
    "overshoot",
    "steady_state_error",
    "peak_voltage",
    "saturation_time",
    "diverged",
)

PEERS = ("python-control", "scipy", "numpy-vectorized")


class PeerDisagreement(RuntimeError):
    """A peer computed a different loop than jaxcart: the comparison would be meaningless."""


# ---------------------------------------------------------------- the workload


def w1_gains(n: int, seed: int = SEED) -> np.ndarray:
    """``n`` gain triples (columns kp [V/m], kd [V s/m], ki [V/(m s)]), float64, reproducible.

    The first rows do not depend on ``n``, so a small batch is a prefix of a large one.
    """
    rng = np.random.default_rng(seed)
    unit = rng.random((n, 3))
    lo = np.array([GAIN_RANGES[k][0] for k in ("kp", "kd", "ki")])
    hi = np.array([GAIN_RANGES[k][1] for k in ("kp", "kd", "ki")])
    return lo + unit * (hi - lo)


def w1_grid(points: int) -> np.ndarray:
    """A ``points``^3 grid over the default ranges of ``jaxcart grid``, rows (kp, kd, ki)."""
    axes = [np.linspace(*GRID_RANGES[k], points) for k in ("kp", "kd", "ki")]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def w1_problem(horizon: float = HORIZON):
    """(plant, controller, experiment) of W1, built in the current JAX precision."""
    plant = jaxcart.handout_plant()
    controller = PID(tau=TAU, v_limit=V_LIMIT, sample_time=SAMPLE_TIME)
    experiment = jaxcart.step(STEP, horizon=horizon, sample_time=SAMPLE_TIME)
    return plant, controller, experiment


# ---------------------------------------------------------------- jaxcart


def reference_positions(plant, controller, experiment, gains) -> np.ndarray:
    """Float64 ``jaxcart.simulate`` positions [m] with EXACT_FORMS (hard clips), one row per
    gain triple. Builds its own float64 problem: pass the W1 setup built in any precision."""
    with jax.enable_x64(True):
        experiment = dataclasses.replace(
            experiment, signal=jnp.asarray(np.asarray(experiment.signal, dtype=float))
        )

        def one(g):
            pid = dataclasses.replace(controller, kp=g[0], kd=g[1], ki=g[2])
            return jaxcart.simulate(plant, pid, experiment, smoothing=jaxcart.EXACT_FORMS).position

        return np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(gains, dtype=jnp.float64)))


def jaxcart_metrics(plant, controller, experiment, gains, dtype) -> dict:
    """``step_metrics_batch`` (EXACT_FORMS) in ``dtype``, as a dict of numpy arrays."""
    x64 = jnp.dtype(dtype) == jnp.float64
    with jax.enable_x64(x64):
        experiment = dataclasses.replace(
            experiment, signal=jnp.asarray(np.asarray(experiment.signal, dtype=float))
        )
        info = step_metrics_batch(plant, controller, experiment, gains, dtype=dtype)
    return {k: np.asarray(v) for k, v in info._asdict().items()}


#: Samples per loop iteration of the gradient row: 1 where loops compile whole (2 ran 0.9x as
#: fast, see :data:`GRAD_CHUNK`), 2 where they run as tasks (1.15-1.4x faster than 1 there),
#: measured on 2 cores.
UNROLL_GRAD = {"whole": 1, "tasks": 2}
#: Runs per chunk of the gradient row where loops compile whole (jaxcart.xlaflags): each of
#: the three tangents then carries 64 runs per array, its loop in the L1 cache; 128, 256
#: runs: 0.9x, 0.85x; unrolled by 2: 0.9x (measured, 2 cores, float32).
GRAD_CHUNK = 64


def smooth_loss(plant, controller, experiment, gains, smoothing=None):
    """A smooth tuning loss of one run [-]: the integral of the squared error (normalized by
    the step) plus a penalty on overshoot beyond 5 %, with the default
    :class:`jaxcart.Smoothing`. Summed inside the simulation loop
    (:func:`jaxcart.accumulators.accumulate`): no trace is stored, so forward-mode tangents ride
    along in the loop's carry."""
    pid = dataclasses.replace(controller, kp=gains[0], kd=gains[1], ki=gains[2])
    # A product, not a quotient per sample: a division is the costliest operation of the
    # loop's tangents (the row 1.5x faster, measured).
    inv_amplitude = 1.0 / (experiment.signal[-1] - experiment.y0)

    def add(acc, k, t, s):
        ise, over = acc
        e = (s.reference - s.position) * inv_amplitude
        z = (s.position - experiment.y0) * inv_amplitude
        return ise + e * e, over + jnp.square(smooth_relu(z - 1.05, 1e-3))

    zero = jnp.zeros((), jnp.result_type(experiment.signal))
    unroll = UNROLL_GRAD["whole" if loops_whole() else "tasks"]
    ise, over = accumulate(
        plant, pid, experiment, (zero, zero), add, smoothing=smoothing, unroll=unroll
    )
    return (ise + 100.0 * over) * experiment.sample_time


def grad_evaluator(plant, controller, experiment, *, chunk: int):
    """f(gains (B, 3)) -> (loss (B,), d loss / d gains (B, 3)) by forward mode (three tangents
    per run, the loss summed inside the loop: nothing stored for a backward pass), in chunks
    of ``chunk`` runs per device through :func:`jaxcart.parallel.sharded_map`."""
    grads = value_and_jacfwd_rows(lambda g, _, p, c, e: smooth_loss(p, c, e, g))

    def one_chunk(gains, p, c, e):
        return grads(gains, None, p, c, e)

    # The batch program's XLA options (the forward row's), and on a CPU copy insertion by
    # region analysis, which spares the tangents' loop its per-iteration copies: 1.2x (with
    # loops compiled whole; 1.15x without; measured, 2 cores). The forward loop gains nothing.
    options = dict(COMPILER_OPTIONS.get(jax.default_backend(), {}))
    if jax.default_backend() == "cpu":
        options["xla_cpu_copy_insertion_use_region_analysis"] = True
    run_all = sharded_map(
        one_chunk, chunk=chunk, cache=False, compiler_options=options, whole_chunks=True
    )

    def run(gains):
        return run_all(jnp.asarray(gains), plant, controller, experiment)

    return run


# ---------------------------------------------------------------- measuring


def _best(fn: Callable[[], object], repeats: int) -> tuple[float, list[float]]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), times


def _max_diff(a: dict, b: dict, names=METRICS) -> dict:
    """Largest |a - b| per metric; equal infinities count as 0, a one-sided inf as inf."""
    out = {}
    for name in names:
        x = np.asarray(a[name], dtype=float)
        y = np.asarray(b[name], dtype=float)
        with np.errstate(invalid="ignore"):
            d = np.where(x == y, 0.0, np.abs(x - y))
        out[name] = float(np.nan_to_num(d, nan=np.inf).max()) if d.size else 0.0
    return out


def _stack(infos: list[dict]) -> dict:
    return {k: np.array([i[k] for i in infos]) for k in infos[0]}


def _stderr(message: str) -> None:
    print(f"bench: {message}", file=sys.stderr, flush=True)


def _check(
    name: str,
    positions: np.ndarray,
    reference: np.ndarray,
    metrics: dict,
    ref_metrics: dict,
    tolerance: float,
) -> dict:
    dy = float(np.max(np.abs(positions - reference))) if positions.size else 0.0
    diffs = _max_diff(metrics, ref_metrics)
    # Times are sample counts: equal unless a crossing sits within the position error.
    time_ok = all(
        diffs[k] <= SAMPLE_TIME * 1.001 for k in ("rise_time", "settling_time", "saturation_time")
    )
    if not (dy <= tolerance) or not time_ok or diffs["diverged"] > 0:
        raise PeerDisagreement(
            f"{name} disagrees with float64 jaxcart.simulate on the W1 runs: max |dy| = "
            f"{dy:.3g} m (tolerance {tolerance:g} m), metric differences {diffs}"
        )
    return {"runs": int(positions.shape[0]), "max_position_diff_m": dy, "max_metric_diff": diffs}


def run_bench(
    *,
    batch: int | None = None,
    quick: bool = False,
    slow_runs: int | None = None,
    numpy_runs: int | None = None,
    grad_runs: int | None = None,
    grid_points: int | None = None,
    repeats: int | None = None,
    check_runs: int = 16,
    progress: Callable[[str], None] | None = _stderr,
    _horizon: float = HORIZON,
) -> dict:
    """Measure W1 for jaxcart and its peers in this process; returns the result as a dict
    (the ``--json`` content).

    batch: gain triples for jaxcart's float32 ``step_metrics_batch`` (default 131072);
    slow_runs: runs of python-control and of scipy, each timed one at a time (3); numpy_runs:
    batch of the vectorized numpy peer (32768); grad_runs: batch of the gradient measurement
    (32768); grid_points: the grid is grid_points^3 (64); repeats: timed calls of each batched
    stage, the median kept (3); check_runs: runs compared with the float64 reference (16).
    ``quick`` lowers the defaults. ``_horizon`` [s] shortens the runs (tests only: the result
    is then not W1 and says so).

    Raises :class:`PeerDisagreement` when a float64 peer's positions differ from float64
    jaxcart by more than ``TOLERANCE`` or its metrics by more than one sample.
    """
    say = progress or (lambda message: None)
    n = _sizes(
        quick,
        batch=batch,
        slow=slow_runs,
        numpy=numpy_runs,
        grad=grad_runs,
        grid=grid_points,
        repeats=repeats,
        check=check_runs,
    )
    gains = w1_gains(max(n["batch"], n["numpy"], n["check"]))
    result = _header(_horizon)
    load_before = _load()

    # Correctness first: the float64 reference, then each peer against it.
    with jax.enable_x64(True):
        problem = w1_problem(_horizon)
    say(f"reference: float64 jaxcart.simulate (EXACT_FORMS) on {n['check']} runs")
    ref = _reference(problem, gains[: n["check"]])
    checks = {"jaxcart-metrics-vs-trace": ref.pop("own_check")}
    rows = [
        _slow_peer(name, fn, problem, gains, ref, n["slow"], checks, say)
        for name, fn in (("python-control", python_control_run), ("scipy", scipy_run))
    ]
    numpy_row, numpy32 = _numpy_peer(problem, gains, ref, n, checks, say, quick)
    rows.append(numpy_row)

    jax_rows, jax32 = _jaxcart_rows(problem, gains, n, result, _horizon, say)
    c_row = _c_kernel(problem, gains[: n["batch"]], ref, jax32, n, checks, say)
    _ceiling_ratios(jax_rows, c_row)
    rows[:0] = [*jax_rows, c_row]
    checks.update(_precision_checks(jax32, numpy32, ref, n))
    result.update(_summary(rows, result, n["batch"], checks))
    result["load_average"] = {
        "before": load_before,
        "after": _load(),
        "note": "1-minute load of this machine; processes running beside the benchmark "
        "lower every rate, jaxcart's (all cores) more than the single-threaded peers'",
    }
    return result


def _sizes(quick: bool, *, batch, slow, numpy, grad, grid, repeats, check) -> dict:
    """The run's sizes: the given ones, else the defaults (smaller with ``quick``)."""
    n = {
        "batch": batch or (16384 if quick else 131072),
        "slow": slow or (1 if quick else 3),
        # numpy's per-call overhead amortizes up to ~32k lanes (measured: 4096 runs reach
        # ~40 % of the float32 rate of 32768; larger batches gain nothing).
        "numpy": numpy or (8192 if quick else 32768),
        # The gradient's rate saturates from 16384 runs on 2 devices (measured, sims/s: 8192
        # 62-68k, 16384 85k, 32768 82k, 65536 89k); 8192 understated it by a quarter.
        "grad": grad or (1024 if quick else 32768),
        "grid": grid or (16 if quick else 64),
        "repeats": repeats or (1 if quick else 3),
    }
    # float64 runs at about half the float32 rate: a smaller batch keeps its row short.
    n["batch64"] = max(1, min(n["batch"], 32768))
    n["check"] = max(check, n["slow"])  # the timed slow runs are checked too
    if min(n.values()) < 1:
        raise ValueError(f"bench sizes must be positive: {n}")
    return n


def _jaxcart_rows(problem, gains, n, result, horizon, say) -> tuple[list, dict]:
    """jaxcart's float32 and float64 rows; the float32 compile time, grid and gradient go into
    ``result``. Returns ([float32 row, float64 row], float32 metrics)."""
    with jax.enable_x64(False):  # exactly float32, whatever jax_enable_x64 says
        problem32 = w1_problem(horizon)
        jax_row, jax32, compile_s = _jaxcart(problem32, gains[: n["batch"]], n["repeats"], say)
        result["compile_s"] = compile_s
        result["grid"] = _grid(problem32, n["grid"], n["repeats"], say)
        result["grad"] = _grad(problem32, n["grad"], n["repeats"], say)
    jax64_row = _jaxcart64(problem, gains[: n["batch64"]], n["repeats"], say)
    return [jax_row, jax64_row], jax32


def _precision_checks(jax32, numpy32, ref, n) -> dict:
    """The float32 rows against the float64 reference and against each other (reported, not
    enforced: float32 rounding may move a crossing by a sample)."""
    check = n["check"]
    m = min(n["numpy"], n["batch"])
    return {
        "jaxcart-float32-vs-float64": {
            "runs": check,
            "max_metric_diff": _max_diff(_head(jax32, check), ref["metrics"]),
        },
        "numpy-float32-vs-jaxcart-float32": {
            "runs": m,
            "max_metric_diff": _max_diff(_head(numpy32, m), _head(jax32, m)),
            "note": "float32 rounding; times are counts of samples, so a crossing near a "
            "threshold may move by a sample or more",
        },
    }


def _summary(rows, result, batch, checks) -> dict:
    """rows (each with its ``jaxcart_ratio``), the ratios, the gradient's rate over the
    forward rate, the checks and the targets met."""
    jax_row, jax64_row, c_row = rows[:3]
    jax_rate = jax_row["sims_per_s"]
    for row in rows:
        if "sims_per_s" in row:
            row["jaxcart_ratio"] = jax_rate / row["sims_per_s"]
    ratios = {row["name"]: row["jaxcart_ratio"] for row in rows[1:] if "jaxcart_ratio" in row}
    grad = result["grad"]
    # The gradient's rate over the forward W1 rate, both medians (wall; and per CPU-second,
    # steadier on a shared machine).
    grad_ratio = {
        "sims_per_s": grad["sims_per_s"] / jax_rate,
        "sims_per_cpu_s": grad["sims_per_cpu_s"] / jax_row["sims_per_cpu_s"],
    }
    no_c = "skipped" in c_row
    return {
        "rows": rows,
        "ratios": ratios,
        "batch": batch,
        "grad_sims_per_s": grad["sims_per_s"],
        "grad_ratio": grad_ratio,
        "grid_sims_per_s": result["grid"]["sims_per_s"],
        "checks": checks,
        "max_peer_position_diff_m": max(checks[p]["max_position_diff_m"] for p in PEERS),
        "targets": {
            "jaxcart_sims_per_s >= 100000": jax_rate >= 1e5,
            "ratio numpy-vectorized >= 30": ratios["numpy-vectorized"] >= 30,
            "ratio python-control >= 30000": ratios["python-control"] >= 3e4,
            "jaxcart >= 50 % of c-kernel per CPU-second": (
                None if no_c else jax_row["ceiling_ratio"] >= 0.5
            ),
            "jaxcart-float64 >= 50 % of c-kernel per CPU-second": (
                None if no_c else jax64_row["ceiling_ratio"] >= 0.5
            ),
            "grad >= 1/4 of jaxcart sims/s": grad_ratio["sims_per_s"] >= 0.25,
        },
    }


def _header(horizon: float) -> dict:
    devices = parallel.devices()
    name = "W1" if horizon == HORIZON else "W1 (shortened horizon: not the benchmark)"
    return {
        "workload": {
            "name": name,
            "step_m": STEP,
            "horizon_s": horizon,
            "sample_time_s": SAMPLE_TIME,
            "samples": int(round(horizon / SAMPLE_TIME)) + 1,
            "v_limit_V": V_LIMIT,
            "v_sat_V": V_LIMIT,
            "tau_s": TAU,
            "derivative_on": "error",
            "gain_ranges": GAIN_RANGES,
            "seed": SEED,
            "plant": "handout_plant()",
        },
        "backend": jax.default_backend(),
        "devices": len(devices),
        "device_kind": devices[0].device_kind,
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "versions": _versions(),
        "tolerance_m": TOLERANCE,
    }


def _head(metrics: dict, k: int) -> dict:
    return {name: v[:k] for name, v in metrics.items()}


def _reference(problem, gains) -> dict:
    """Float64 jaxcart positions and metrics of the check runs, and a check of jaxcart's
    streamed metrics against :func:`trace_metrics` on the same traces."""
    plant, controller, _ = problem
    positions = reference_positions(*problem, gains)
    metrics = jaxcart_metrics(*problem, gains, jnp.float64)
    on_trace = _stack(
        [
            trace_metrics(
                y,
                np.zeros(1),
                np.zeros(1),
                r_final=STEP,
                y0=0.0,
                ts=SAMPLE_TIME,
                limit=float(voltage_limit(plant, controller)),
            )
            for y in positions
        ]
    )
    own = ("rise_time", "settling_time", "overshoot", "steady_state_error", "diverged")
    own_check = {"runs": len(gains), "max_metric_diff": _max_diff(metrics, on_trace, own)}
    return {"positions": positions, "metrics": metrics, "own_check": own_check}


def _slow_peer(name, fn, problem, gains, ref, runs, checks, say) -> dict:
    """Time ``runs`` one-at-a-time runs of a peer; the same runs are checked against ``ref``."""
    say(f"{name}: {runs} run(s), one at a time")
    traces, infos, times = [], [], []
    for g in gains[:runs]:
        t0 = time.perf_counter()
        y, info = fn(*problem, g)
        times.append(time.perf_counter() - t0)
        traces.append(y)
        infos.append(info)
    checks[name] = _check(
        name,
        np.array(traces),
        ref["positions"][:runs],
        _stack(infos),
        _head(ref["metrics"], runs),
        TOLERANCE,
    )
    rate = runs / sum(times)
    say(f"{name}: {rate:.3g} sims/s, max |dy| = {checks[name]['max_position_diff_m']:.2g} m")
    return {"name": name, "sims_per_s": rate, "runs": runs, "dtype": "float64", "seconds": times}


def _numpy_peer(problem, gains, ref, n, checks, say, quick) -> tuple[dict, dict]:
    """Check the numpy peer in float64, then time it in both precisions (the faster is its
    figure); returns its row and its float32 metrics."""
    k = n["check"]
    say(f"numpy-vectorized: float64 check on {k} runs")
    info, trace = numpy_batch(*problem, gains[:k], record=k)
    checks["numpy-vectorized"] = _check(
        "numpy-vectorized", trace, ref["positions"], info, ref["metrics"], TOLERANCE
    )
    runs = n["numpy"]
    timing, outputs = {}, {}
    for dtype in ("float32", "float64"):
        say(f"numpy-vectorized: {runs} runs in {dtype}")

        def call(dtype=dtype):
            outputs[dtype] = numpy_batch(*problem, gains[:runs], dtype=dtype)[0]

        best, times = _best(call, n["repeats"])
        timing[dtype] = {"sims_per_s": runs / best, "seconds": times}
    fastest = max(timing, key=lambda k: timing[k]["sims_per_s"])
    # How the rate depends on the batch (small batches pay numpy's per-call overhead).
    by_batch = {}
    for size in () if quick else (4096, 16384):
        if size < runs:
            t0 = time.perf_counter()
            numpy_batch(*problem, gains[:size], dtype=fastest)
            by_batch[str(size)] = size / (time.perf_counter() - t0)
    by_batch[str(runs)] = timing[fastest]["sims_per_s"]
    rate = timing[fastest]["sims_per_s"]
    say(f"numpy-vectorized: {rate:.3g} sims/s ({fastest})")
    row = {
        "name": "numpy-vectorized",
        "sims_per_s": rate,
        "runs": runs,
        "dtype": fastest,
        "seconds": timing[fastest]["seconds"],
        "by_dtype": timing,
        "by_batch": by_batch,
    }
    return row, outputs["float32"]


def _timed(fn: Callable[[], object], repeats: int, cpu_clock=time.process_time) -> dict:
    """Median wall and CPU seconds of ``repeats`` calls (``cpu_clock``: process CPU time, all
    threads, by default; ``time.thread_time`` for code that runs in the calling thread)."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), cpu_clock()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(cpu_clock() - c0)
    median = {"wall": float(np.median(wall)), "cpu": float(np.median(cpu))}
    return {**median, "seconds": wall, "cpu_seconds": cpu}


def _jaxcart_row(name, problem, gains, dtype, repeats, say) -> tuple[dict, object, float]:
    """One step_metrics_batch row: sims/s (median wall), sims per CPU-second (median process
    CPU time, every thread), first call; returns (row, metrics, first call [s])."""
    devs = parallel.devices()
    kind = devs[0].device_kind
    say(
        f"{name}: step_metrics_batch {jnp.dtype(dtype).name}, {len(gains)} runs on "
        f"{len(devs)} {jax.default_backend()} device(s) ({kind})"
    )

    def call():
        return jax.block_until_ready(step_metrics_batch(*problem, gains, dtype=dtype))

    t0 = time.perf_counter()
    info = call()
    first = time.perf_counter() - t0
    t = _timed(call, repeats)
    rate, cpu_rate = len(gains) / t["wall"], len(gains) / max(t["cpu"], 1e-9)
    say(f"{name}: {rate:.4g} sims/s, {cpu_rate:.4g} per CPU-second (first call {first:.2f} s)")
    row = {
        "name": name,
        "sims_per_s": rate,
        "sims_per_cpu_s": cpu_rate,
        "runs": len(gains),
        "dtype": jnp.dtype(dtype).name,
        "devices": len(devs),
        "device_kind": kind,
        "seconds": t["seconds"],
        "cpu_seconds": t["cpu_seconds"],
        "first_call_s": first,
    }
    return row, info, first - t["wall"]


def _jaxcart(problem32, gains, repeats, say) -> tuple[dict, dict, float]:
    """The figure: float32 step_metrics_batch; returns its row, its metrics and the compile
    time (first call minus the median steady-state call)."""
    row, info, compile_s = _jaxcart_row("jaxcart", problem32, gains, jnp.float32, repeats, say)
    metrics = {k: np.asarray(v) for k, v in info._asdict().items()}
    return row, metrics, max(0.0, compile_s)


def _jaxcart64(problem64, gains, repeats, say) -> dict:
    """The float64 row of step_metrics_batch (the precision of the reference)."""
    with jax.enable_x64(True):
        row, _, _ = _jaxcart_row("jaxcart-float64", problem64, gains, jnp.float64, repeats, say)
    return row


def _c_kernel(problem64, gains, ref, jax32, n, checks, say) -> dict:
    """The ceiling row: the C kernel of W1 (tuning/benchmark/ckernel.py), checked in float64
    against the
    reference like every peer (positions within TOLERANCE, metrics to a sample) and in float32
    against jaxcart float32, then timed in both precisions (vectorized across runs, one
    thread, per CPU-second of the calling thread) and once as the plain scalar loop.
    Without a C compiler the row says why it was skipped."""
    try:
        _, build = ckernel.load()
    except ckernel.KernelUnavailable as exc:
        say(f"c-kernel: skipped ({exc})")
        return {"name": "c-kernel", "skipped": str(exc)}
    say(f"c-kernel: built with {build['version']} {' '.join(build['flags'])}")
    k = n["check"]
    info, trace = ckernel.run_w1(*problem64, gains[:k], record=k)
    checks["c-kernel"] = _check(
        "c-kernel", trace, ref["positions"], info, ref["metrics"], TOLERANCE
    )
    m = min(len(gains), len(next(iter(jax32.values()))))
    info32, _ = ckernel.run_w1(*problem64, gains[:m], dtype="float32")
    checks["c-kernel-float32-vs-jaxcart-float32"] = {
        "runs": m,
        "max_metric_diff": _max_diff(info32, _head(jax32, m)),
        "note": "float32 rounding (the kernel's ZOH coefficients come from scipy's expm)",
    }
    timing = {}
    for dtype in ("float32", "float64"):
        say(f"c-kernel: {len(gains)} runs in {dtype}, one thread")

        def call(d=dtype):
            ckernel.run_w1(*problem64, gains, dtype=d)

        t = _timed(call, n["repeats"], time.thread_time)
        timing[dtype] = {
            "sims_per_s": len(gains) / t["wall"],
            "sims_per_cpu_s": len(gains) / max(t["cpu"], 1e-9),
            "seconds": t["seconds"],
            "cpu_seconds": t["cpu_seconds"],
            "lanes": ckernel.LANES[dtype],
        }
    scalar_runs = min(len(gains), 4096)
    t = _timed(
        lambda: ckernel.run_w1(*problem64, gains[:scalar_runs], lanes=False), 1, time.thread_time
    )
    scalar = {
        "runs": scalar_runs,
        "dtype": "float64",
        "sims_per_cpu_s": scalar_runs / max(t["cpu"], 1e-9),
    }
    row = {
        "name": "c-kernel",
        **{k: timing["float32"][k] for k in ("sims_per_s", "sims_per_cpu_s", "seconds")},
        "runs": len(gains),
        "dtype": "float32",
        "threads": 1,
        "by_dtype": timing,
        "scalar_loop": scalar,
        "build": build,
    }
    say(
        f"c-kernel: {row['sims_per_cpu_s']:.4g} sims per CPU-second (float32), "
        f"{timing['float64']['sims_per_cpu_s']:.4g} (float64), "
        f"{scalar['sims_per_cpu_s']:.4g} (scalar loop, float64)"
    )
    return row


def _ceiling_ratios(jax_rows, c_row) -> None:
    """Each jaxcart row's rate per CPU-second over the C kernel's in the same precision. On a
    GPU, CPU time says nothing of the device's work: there the ratio is jaxcart's sims/s
    (wall) over the kernel's per CPU-second of one core, and ``ceiling_basis`` says so."""
    if "skipped" in c_row:
        return
    on_cpu = jax.default_backend() == "cpu"
    for row in jax_rows:
        c_rate = c_row["by_dtype"][row["dtype"]]["sims_per_cpu_s"]
        own = row["sims_per_cpu_s"] if on_cpu else row["sims_per_s"]
        row["ceiling_ratio"] = own / c_rate
        row["ceiling_basis"] = (
            "per CPU-second, both" if on_cpu else "jaxcart sims/s on the devices vs one CPU core"
        )


def _grid(problem32, points, repeats, say) -> dict:
    """Throughput of a points^3 grid through step_metrics_batch (what `jaxcart grid` runs)."""
    grid = w1_grid(points)
    say(f"grid: {points}^3 = {grid.shape[0]} runs, float32")

    def call():
        jax.block_until_ready(step_metrics_batch(*problem32, grid, dtype=jnp.float32))

    call()  # its chunk size may differ from the batch's: compile outside the timing
    best, times = _best(call, max(1, repeats - 1))
    rate = grid.shape[0] / best
    say(f"grid: {rate:.4g} sims/s")
    return {
        "points": points,
        "runs": int(grid.shape[0]),
        "ranges": GRID_RANGES,
        "sims_per_s": rate,
        "seconds": times,
    }


def _grad(problem32, runs, repeats, say) -> dict:
    """Simulation plus gradient of :func:`smooth_loss` with respect to the gains, float32,
    forward mode, sharded over the devices in chunks of :data:`GRAD_CHUNK` runs where loops
    compile whole (else of the wide chunks, forward mode stores nothing per step). Timed like
    the jaxcart rows: median wall and process CPU seconds of ``repeats`` calls."""
    n_dev = len(jax.devices())
    chunk = max(1, min(default_chunk(GRAD_CHUNK, WIDE_CHUNK), runs // n_dev))
    unit = chunk * n_dev
    runs = -(-runs // unit) * unit
    say(
        f"grad: forward-mode gradient (3 tangents, loss summed in the loop) float32, {runs} "
        f"runs, chunks of {chunk} on {n_dev} device(s)"
    )
    evaluate = grad_evaluator(*problem32, chunk=chunk)
    gains = jnp.asarray(w1_gains(runs), dtype=jnp.float32)
    t0 = time.perf_counter()
    loss, grad = jax.block_until_ready(evaluate(gains))
    first = time.perf_counter() - t0
    t = _timed(lambda: jax.block_until_ready(evaluate(gains)), repeats)
    rate, cpu_rate = runs / t["wall"], runs / max(t["cpu"], 1e-9)
    say(f"grad: {rate:.4g} sims/s, {cpu_rate:.4g} per CPU-second")
    finite = bool(np.all(np.isfinite(np.asarray(grad))) and np.all(np.isfinite(np.asarray(loss))))
    return {
        "sims_per_s": rate,
        "sims_per_cpu_s": cpu_rate,
        "runs": runs,
        "chunk": chunk,
        "devices": n_dev,
        "dtype": "float32",
        "loss": "ISE/A^2 + 100 * int smooth_relu(z - 1.05)^2 dt, default Smoothing",
        "mode": "forward (jacfwd: one tangent per gain, loss accumulated in the loop)",
        "sharded": True,
        "seconds": t["seconds"],
        "cpu_seconds": t["cpu_seconds"],
        "compile_s": max(0.0, first - t["wall"]),
        "all_finite": finite,
    }


def _load() -> float | None:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def _versions() -> dict:
    return {
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "control": control.__version__,
    }


def _fmt(x: float) -> str:
    return f"{x:,.0f}" if x >= 1000 else f"{x:.3g}"


def format_table(result: dict) -> str:
    """The result as a text table: sims/s (and per CPU-second) per implementation, jaxcart's
    ratio to each, and the jaxcart rows' fraction of the C kernel's ceiling."""
    w = result["workload"]
    lines = [
        f"{w['name']}: PID + {w['v_limit_V']:g} V saturation, {w['step_m']:g} m step, "
        f"{w['horizon_s']:g} s at {w['sample_time_s'] * 1e3:g} ms ({w['samples']} samples)",
        f"jax on {result['devices']} {result['backend']} device(s) "
        f"({result.get('device_kind', '?')}); {result.get('platform', '?')}, "
        f"{result['cpu_count']} CPUs",
        f"{'implementation':<24}{'runs':>8}  {'dtype':<9}{'sims/s':>11}{'per CPU-s':>11}"
        f"{'jaxcart/peer':>14}{'of c-kernel':>13}{'max |dy| [m]':>14}",
    ]
    lines += [_row_line(row, result["checks"]) for row in result["rows"]]
    lines += _grad_and_grid_lines(result)
    c_row = next((r for r in result["rows"] if r["name"] == "c-kernel"), None)
    if c_row is not None and "skipped" not in c_row:
        scalar = c_row["scalar_loop"]["sims_per_cpu_s"]
        lines.append(
            f"c-kernel: {c_row['build']['version']} {' '.join(c_row['build']['flags'])}, one "
            f"thread, {c_row['by_dtype']['float32']['lanes']} (float32) / "
            f"{c_row['by_dtype']['float64']['lanes']} (float64) runs per vector block; "
            f"float64 {_fmt(c_row['by_dtype']['float64']['sims_per_cpu_s'])} per CPU-s, "
            f"scalar loop {_fmt(scalar)}. 'of c-kernel': per CPU-second, same precision."
        )
    lines.append(_targets_line(result))
    load = result.get("load_average") or {}
    if load.get("before") is not None:
        lines.append(
            f"load average (1 min) before/after: {load['before']:.2f} / "
            f"{load['after']:.2f} on {result['cpu_count']} CPUs"
        )
    return "\n".join(lines)


def _row_line(row: dict, checks: dict) -> str:
    """One implementation's line of :func:`format_table`."""
    if "skipped" in row:
        return f"{row['name']:<24}  skipped: {row['skipped']}"
    dy = checks.get(row["name"], {}).get("max_position_diff_m")
    cpu = row.get("sims_per_cpu_s")
    ceiling = row.get("ceiling_ratio")
    return (
        f"{row['name']:<24}{row['runs']:>8}  {row['dtype']:<9}{_fmt(row['sims_per_s']):>11}"
        f"{'' if cpu is None else _fmt(cpu):>11}{_fmt(row['jaxcart_ratio']) + 'x':>14}"
        f"{'' if ceiling is None else f'{ceiling:.0%}':>13}"
        f"{'' if dy is None else f'{dy:>14.2g}'}"
    )


def _grad_and_grid_lines(result: dict) -> list[str]:
    """The gradient's and the grid's lines of :func:`format_table`, and the compile times."""
    grad, grid = result["grad"], result["grid"]
    grad_cpu = grad.get("sims_per_cpu_s")
    grad_ratio = result.get("grad_ratio")
    return [
        f"{'grad (sim + d/d gains)':<24}{grad['runs']:>8}  {'float32':<9}"
        f"{_fmt(result['grad_sims_per_s']):>11}{'' if grad_cpu is None else _fmt(grad_cpu):>11}"
        + (
            ""
            if grad_ratio is None
            else f"   {grad_ratio['sims_per_s']:.3f} of jaxcart's sims/s "
            f"({grad_ratio['sims_per_cpu_s']:.3f} per CPU-s)"
        ),
        f"{'grid ' + str(grid['points']) + '^3':<24}{grid['runs']:>8}  {'float32':<9}"
        f"{_fmt(result['grid_sims_per_s']):>11}",
        f"jit compile: {result['compile_s']:.2f} s (step_metrics_batch), "
        f"{grad['compile_s']:.2f} s (grad). max |dy|: positions against float64 "
        f"jaxcart.simulate (tolerance {result['tolerance_m']:g} m).",
    ]


def _targets_line(result: dict) -> str:
    """Which targets the run met, each with its figure."""
    ratios = result["ratios"]
    grad_ratio = result.get("grad_ratio")
    jax_row, jax64_row = result["rows"][0], result["rows"][1]
    shown = {
        "jaxcart_sims_per_s >= 100000": _fmt(jax_row["sims_per_s"]),
        "ratio numpy-vectorized >= 30": _fmt(ratios["numpy-vectorized"]) + "x",
        "ratio python-control >= 30000": _fmt(ratios["python-control"]) + "x",
        "jaxcart >= 50 % of c-kernel per CPU-second": (
            f"{jax_row['ceiling_ratio']:.0%}" if "ceiling_ratio" in jax_row else "no compiler"
        ),
        "jaxcart-float64 >= 50 % of c-kernel per CPU-second": (
            f"{jax64_row['ceiling_ratio']:.0%}" if "ceiling_ratio" in jax64_row else "no compiler"
        ),
        "grad >= 1/4 of jaxcart sims/s": (
            "" if grad_ratio is None else f"{grad_ratio['sims_per_s']:.3f}"
        ),
    }
    return "targets: " + "; ".join(
        f"{name} "
        + {True: "met", False: "NOT met", None: "not measured"}[ok]
        + f" ({shown.get(name, '')})"
        for name, ok in result["targets"].items()
    )


def to_json(value):
    """``value`` with numpy scalars made plain and infinities written as the string "inf"."""
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_json(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value
