"""The ceiling of workload W1: a minimal C kernel of exactly W1, built with the system's C
compiler and called through ctypes (the "c-kernel" row of ``jaxcart bench``).

The source is ``tuning/benchmark/w1.c`` (shipped with the package). It is compiled once per
source, compiler and flags into the user's cache folder next to the JAX cache
(``~/.cache/jaxcart/ckernel``, safe to delete), with ``-O3 -march=native`` where the compiler
accepts it. The kernel runs LANES runs at a time so the compiler vectorizes across runs (the
machine's limit for this loop); :func:`run_w1` with ``lanes=False`` runs the plain scalar loop.

Without a compiler, :func:`load` raises :class:`KernelUnavailable` saying why.
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from jaxcart.cache import cache_dir
from jaxcart.effects import Saturation
from jaxcart.metrics import SETTLING_BAND
from jaxcart.params import voltage_limit
from jaxcart.smooth_sim import DIVERGED_POSITION
from tuning.benchmark.peers import zoh_matrices

SOURCE = Path(__file__).with_name("w1.c")
#: Flags tried in order: the first the compiler accepts builds the kernel. No -ffast-math:
#: the metrics rely on IEEE comparisons (a NaN position marks a diverged run).
FLAG_SETS = (("-O3", "-march=native"), ("-O3",))
#: Runs per vector block in the source (W1_KERNEL(..., LANES)): float32 64, float64 16.
LANES = {"float32": 64, "float64": 16}
_C_TYPES = {"float32": ctypes.c_float, "float64": ctypes.c_double}
METRIC_NAMES = ("rise_time", "settling_time", "overshoot", "steady_state_error", "peak_voltage")


class KernelUnavailable(RuntimeError):
    """No C compiler, or the kernel did not build: the message says which."""


def compiler() -> str | None:
    """The C compiler: $CC if set, else cc, gcc or clang from PATH; None when there is none."""
    names = [os.environ["CC"]] if os.environ.get("CC") else ["cc", "gcc", "clang"]
    for name in names:
        path = shutil.which(name)
        if path:
            return path
    return None


def cache_folder() -> Path:
    """Where built kernels are kept: beside the persistent JAX cache (jaxcart.cache)."""
    return cache_dir().parent / "ckernel"


_LOADED: dict = {}


def load() -> tuple[ctypes.CDLL, dict]:
    """The built kernel (compiled on first use, then from the cache) and how it was built:
    {"compiler", "version", "flags", "path"}. Raises :class:`KernelUnavailable`."""
    cc = compiler()
    if cc is None:
        raise KernelUnavailable("no C compiler on PATH (looked for $CC, cc, gcc, clang)")
    if cc in _LOADED:
        return _LOADED[cc]
    try:
        version = subprocess.run(
            [cc, "--version"], capture_output=True, text=True, timeout=30
        ).stdout.splitlines()[0]
    except (OSError, IndexError, subprocess.SubprocessError) as exc:
        raise KernelUnavailable(f"C compiler {cc} does not run: {exc}") from exc
    source = SOURCE.read_bytes()
    errors = []
    for flags in FLAG_SETS:
        key = hashlib.sha256(source + "\0".join((cc, version, *flags)).encode()).hexdigest()
        path = cache_folder() / f"w1-{key[:16]}.so"
        if not path.exists():
            error = _build(cc, flags, path)
            if error:
                errors.append(f"{' '.join(flags)}: {error}")
                continue
        lib = ctypes.CDLL(str(path))
        _declare(lib)
        _LOADED[cc] = (
            lib,
            {"compiler": cc, "version": version, "flags": list(flags), "path": str(path)},
        )
        return _LOADED[cc]
    raise KernelUnavailable(f"{cc} did not build {SOURCE.name}: " + "; ".join(errors))


def _build(cc: str, flags, path: Path) -> str | None:
    """Compile into a temporary name, then rename: a concurrent or killed build leaves no
    half-written library. Returns the compiler's complaint, None on success."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=path.parent)
        os.close(fd)
    except OSError as exc:
        return f"cannot write {path.parent} ({exc.strerror})"
    cmd = [cc, *flags, "-shared", "-fPIC", "-o", tmp, str(SOURCE), "-lm"]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        if done.returncode != 0:
            return (done.stderr.strip().splitlines() or ["failed"])[-1]
        os.replace(tmp, path)
        return None
    except (OSError, subprocess.SubprocessError) as exc:
        return str(exc)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _declare(lib) -> None:
    i64, u8 = ctypes.c_int64, ctypes.POINTER(ctypes.c_uint8)
    for dtype, real in _C_TYPES.items():
        p = ctypes.POINTER(real)
        for kind in ("lanes", "scalar"):
            fn = getattr(lib, f"w1_{dtype.replace('float', 'f')}_{kind}")
            fn.restype = None
            fn.argtypes = [i64, p, i64, p, p, p, p, p, p, p, p, u8, i64, p]


def coefficients(plant, controller, experiment) -> np.ndarray:
    """The 15 numbers the kernel reads (float64; cast by :func:`run_w1`): ts [s], the PID
    filter's tau [s] and gain = 1/(tau+Ts) [1/s], v_limit, v_sat and the
    effective limit [V], the exact ZOH step a01 [s], a11 [-], b0 [m/V], b1 [m/(s V)], y0 [m],
    yd0 [m/s], 1/amplitude [1/m], the settling band [m], the divergence position [m].

    Only W1's loop: a linear plant with at most an amplifier saturation, derivative on
    error, no anti-windup; anything else raises ValueError naming what is not modelled."""
    other = [type(e).name for e in plant.effects if not isinstance(e, Saturation)]
    if other:
        raise ValueError(f"the C kernel models W1's linear plant; not {', '.join(other)}")
    if controller.derivative_on != "error" or controller.anti_windup != "none":
        raise ValueError("the C kernel implements W1's PID: derivative on error, no anti-windup")
    if experiment.kind != "closed_loop":
        raise ValueError(f"the C kernel runs closed-loop steps, not {experiment.kind!r}")
    ts = float(experiment.sample_time)
    ad, bd = zoh_matrices(plant, ts)
    if ad[0, 0] != 1.0 or ad[1, 0] != 0.0:
        raise ValueError("the C kernel assumes a plant without a position-dependent force")
    tau = float(controller.tau)
    sat = [float(e.v_sat) for e in plant.effects]
    r = np.asarray(experiment.signal, dtype=float)
    amplitude = float(r[-1]) - float(experiment.y0)
    return np.array(
        [
            ts,
            tau,
            1.0 / (tau + ts),
            float(controller.v_limit),
            min(sat, default=math.inf),
            float(voltage_limit(plant, controller)),
            ad[0, 1],
            ad[1, 1],
            bd[0],
            bd[1],
            float(experiment.y0),
            float(experiment.yd0),
            1.0 / amplitude,
            SETTLING_BAND * abs(amplitude),
            DIVERGED_POSITION,
        ]
    )


def run_w1(plant, controller, experiment, gains, *, dtype="float64", lanes=True, record=0):
    """W1 for each row (kp [V/m], kd [V s/m], ki [V/(m s)]) of ``gains`` in the C kernel.

    Returns (metrics dict of numpy arrays, the names of :class:`jaxcart.StepInfo`; positions
    y_k [m] of the first ``record`` runs, shape (record, n)). Single-threaded.
    """
    lib, _ = load()
    dtype = np.dtype(dtype).name
    if dtype not in _C_TYPES:
        raise ValueError(f"dtype {dtype}: the kernel is built for float32 and float64")
    fn = getattr(lib, f"w1_{dtype.replace('float', 'f')}_{'lanes' if lanes else 'scalar'}")
    coef = np.ascontiguousarray(coefficients(plant, controller, experiment), dtype=dtype)
    r = np.ascontiguousarray(np.asarray(experiment.signal, dtype=float), dtype=dtype)
    g = np.ascontiguousarray(gains, dtype=dtype)
    if g.ndim != 2 or g.shape[1] != 3:
        raise ValueError(f"gains must have shape (B, 3) for (kp, kd, ki); got {g.shape}")
    b, n = g.shape[0], r.size
    record = int(min(record, b))
    out = {name: np.empty(b, dtype) for name in (*METRIC_NAMES, "saturation_time")}
    diverged = np.zeros(b, np.uint8)
    trace = np.empty((record, n), dtype)
    ptr = _C_TYPES[dtype]

    def p(a):
        return a.ctypes.data_as(ctypes.POINTER(ptr))

    fn(
        b, p(g), n, p(r), p(coef),
        *(p(out[k]) for k in (*METRIC_NAMES, "saturation_time")),
        diverged.ctypes.data_as(ctypes.POINTER(ctypes.c_uint8)),
        record, p(trace),
    )  # fmt: skip
    out["diverged"] = diverged.astype(bool)
    return out, trace
