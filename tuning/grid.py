"""Batched evaluation of PID gain grids (or any list of gain triples).

Every point (kp, kd, ki) of a kp x kd x ki grid is simulated with the digital loop of the lab
(hard clip, the exact forms) and its step metrics are streamed out without storing the run:
settling time [s], overshoot [%], rise time [s], steady-state error [m], peak voltage [V], time
in saturation [s], and whether it meets the specification (settling < ``settling_time`` and
overshoot < ``overshoot``, not diverged: :meth:`jaxcart.StepInfo.meets`).

Memory stays bounded for any grid: the gains of a block of points are generated from the axes
when the block is evaluated (the (B, 3) gain array of the whole grid is never built), each block
goes through :func:`jaxcart.batch.step_metrics_batch` (chunked, sharded over every JAX device)
and its metrics are written into preallocated arrays, about 30 bytes per point.

>>> import numpy as np, jaxcart as jc
>>> res = grid_search(jc.handout_plant(), jc.PID(v_limit=6.0), jc.step(0.5, horizon=1.5),
...                   np.linspace(40, 80, 3), np.linspace(4, 8, 3), [0.0])
>>> res.info.settling_time.shape
(3, 3, 1)
"""

from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart.batch import DEFAULT_CHUNK, step_metrics_batch
from jaxcart.errors import UserError
from jaxcart.metrics import StepInfo
from jaxcart.smooth import EXACT_FORMS

#: Chunks per device in one evaluated block: the progress granularity (65,536 points per
#: block on 2 devices); also what bounds the working set beside the output arrays.
CHUNKS_PER_BLOCK = 8

#: Metric names with their units, in the order they are reported.
METRICS = {
    "settling_time": "s",
    "overshoot": "%",
    "rise_time": "s",
    "steady_state_error": "m",
    "peak_voltage": "V",
    "saturation_time": "s",
}
GAIN_UNITS = {"kp": "V/m", "kd": "V s/m", "ki": "V/(m s)"}


@dataclass(frozen=True)
class GridResult:
    """Step metrics of a batch of gain triples.

    info: :class:`jaxcart.StepInfo` of arrays, each of ``shape`` ((nkp, nkd, nki) for a grid,
        (B,) for a list): rise/settling/saturation time [s], overshoot [%], steady-state
        error [m], peak voltage [V], diverged (bool)
    feasible: bool array of ``shape``, True where the point meets the specification
    best_index: index (into ``shape``) of the best feasible point (smallest settling time,
        ties broken by overshoot); when none is feasible, of the point closest to feasibility
    best_feasible: whether the best point is feasible (False: none is)
    axes: (kp [V/m], kd [V s/m], ki [V/(m s)]) 1-D axes of a grid; None for a list
    gains: (B, 3) rows (kp, kd, ki) of a list; None for a grid (see :meth:`gains_at`)
    settling_spec: settling time bound [s]; overshoot_spec: overshoot bound [%]
    dtype: the floating type of the evaluation ("float32" or "float64")
    elapsed: wall time of the evaluation [s] (compilation included)
    """

    info: StepInfo
    feasible: np.ndarray
    best_index: tuple[int, ...]
    best_feasible: bool
    axes: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    gains: np.ndarray | None
    settling_spec: float
    overshoot_spec: float
    dtype: str
    elapsed: float

    @property
    def shape(self) -> tuple[int, ...]:
        return self.feasible.shape

    @property
    def n_points(self) -> int:
        return int(self.feasible.size)

    @property
    def n_feasible(self) -> int:
        return int(np.count_nonzero(self.feasible))

    @property
    def points_per_second(self) -> float:
        return self.n_points / self.elapsed if self.elapsed > 0 else float("inf")

    def gains_at(self, index) -> tuple[float, float, float]:
        """(kp [V/m], kd [V s/m], ki [V/(m s)]) of the point at ``index`` (into ``shape``)."""
        if self.axes is None:
            return tuple(float(g) for g in self.gains[index])
        return tuple(float(axis[i]) for axis, i in zip(self.axes, index, strict=True))

    @property
    def best_gains(self) -> tuple[float, float, float]:
        return self.gains_at(self.best_index)

    @property
    def best_info(self) -> StepInfo:
        """:class:`StepInfo` (Python scalars) of the best point, as the grid computed it."""
        return StepInfo(*(v[self.best_index].item() for v in self.info))


# ---------------------------------------------------------------- evaluation


def gain_axis(lo: float, hi: float, n: int) -> np.ndarray:
    """``n`` evenly spaced gains from ``lo`` to ``hi`` (both included; ``lo`` when n = 1)."""
    return np.linspace(float(lo), float(hi), int(n))


def grid_search(
    plant,
    controller,
    experiment,
    kp,
    kd,
    ki,
    *,
    settling_time: float = 1.0,
    overshoot: float = 5.0,
    dtype=jnp.float32,
    smoothing=EXACT_FORMS,
    chunk: int = DEFAULT_CHUNK,
    progress=None,
) -> GridResult:
    """Evaluate every point of the grid kp x kd x ki (1-D axes [V/m], [V s/m], [V/(m s)]).

    plant, controller (its other settings: tau, v_limit, ...), experiment: a closed-loop step,
    as for :func:`jaxcart.simulate`. settling_time [s], overshoot [%]: the specification.
    dtype: ``jnp.float32`` (default, fast) or ``jnp.float64``; the evaluation runs in exactly
    that precision whatever ``jax_enable_x64`` says. smoothing: default the exact forms (hard
    clip), right for plants without friction. ``progress(done, total)`` after each block.
    Metric arrays are shaped (len(kp), len(kd), len(ki)).
    """
    _check_spec(settling_time, overshoot)
    axes = tuple(_axis(name, a) for name, a in (("kp", kp), ("kd", kd), ("ki", ki)))
    shape = tuple(a.size for a in axes)

    def rows(start, stop):
        i, j, k = np.unravel_index(np.arange(start, stop), shape)
        return np.stack([axes[0][i], axes[1][j], axes[2][k]], axis=1)

    flat, elapsed = _evaluate(
        plant,
        controller,
        experiment,
        int(np.prod(shape)),
        rows,
        dtype=dtype,
        smoothing=smoothing,
        chunk=chunk,
        progress=progress,
    )
    return _result(flat, shape, axes, None, settling_time, overshoot, dtype, elapsed)


def evaluate_list(
    plant,
    controller,
    experiment,
    gains,
    *,
    settling_time: float = 1.0,
    overshoot: float = 5.0,
    dtype=jnp.float32,
    smoothing=EXACT_FORMS,
    chunk: int = DEFAULT_CHUNK,
    progress=None,
) -> GridResult:
    """Evaluate each row (kp [V/m], kd [V s/m], ki [V/(m s)]) of ``gains`` (shape (B, 3)).

    Same options as :func:`grid_search`; the metric arrays are shaped (B,).
    """
    _check_spec(settling_time, overshoot)
    gains = np.asarray(gains, dtype=float)
    if gains.ndim != 2 or gains.shape[1] != 3 or gains.shape[0] < 1:
        raise UserError(f"gains must have shape (B, 3) with rows (kp, kd, ki); got {gains.shape}")
    if not np.all(np.isfinite(gains)):
        raise UserError("gains contain a value that is not finite; give finite numbers")
    flat, elapsed = _evaluate(
        plant,
        controller,
        experiment,
        gains.shape[0],
        lambda start, stop: gains[start:stop],
        dtype=dtype,
        smoothing=smoothing,
        chunk=chunk,
        progress=progress,
    )
    return _result(flat, gains.shape[:1], None, gains, settling_time, overshoot, dtype, elapsed)


def _check_spec(settling_time, overshoot):
    if not (settling_time > 0 and overshoot > 0):
        raise UserError(
            f"specification: settling time {settling_time} s and overshoot {overshoot} % "
            "must both be positive"
        )


def _axis(name, values) -> np.ndarray:
    axis = np.atleast_1d(np.asarray(values, dtype=float))
    if axis.ndim != 1 or axis.size < 1:
        raise UserError(f"{name}: give a 1-D list of at least one gain; got shape {axis.shape}")
    if not np.all(np.isfinite(axis)):
        raise UserError(f"{name}: every gain must be a finite number; got {axis}")
    return axis


def _evaluate(plant, controller, experiment, n, rows, *, dtype, smoothing, chunk, progress):
    """Metrics of the n points whose gains ``rows(start, stop)`` gives, block by block."""
    if experiment.kind != "closed_loop":
        raise UserError(f"a gain grid needs a closed-loop step experiment, not {experiment.kind}")
    if any(e.stage == "force" for e in plant.effects) and smoothing == EXACT_FORMS:
        raise UserError(
            "the exact (hard) forms are for saturation only; with friction in the plant pass a "
            "smoothing (jaxcart.Smoothing) to the grid"
        )
    dtype = np.dtype(dtype)
    if dtype not in (np.float32, np.float64):
        raise UserError(f"dtype {dtype}: use float32 or float64")
    # Same block size on every call (the last one padded) so the evaluator compiles once.
    block = min(n, len(jax.devices()) * chunk * CHUNKS_PER_BLOCK)
    flat = {name: np.empty(n, dtype) for name in StepInfo._fields}
    flat["diverged"] = np.empty(n, bool)
    start_time = time.perf_counter()
    # Exactly the requested precision whatever jax_enable_x64 says globally: float64 needs it
    # on (the command line runs with it off); float32 must not pick up the default float64.
    with jax.enable_x64(dtype == np.float64):
        for start in range(0, n, block):
            stop = min(n, start + block)
            gains = rows(start, stop)
            if stop - start < block:
                gains = np.concatenate([gains, np.repeat(gains[-1:], block - (stop - start), 0)])
            info = step_metrics_batch(
                plant,
                controller,
                experiment,
                gains,
                smoothing=smoothing,
                chunk=chunk,
                dtype=dtype.type,
            )
            for name, values in zip(StepInfo._fields, info, strict=True):
                flat[name][start:stop] = np.asarray(values)[: stop - start]
            if progress is not None:
                progress(stop, n)
    elapsed = time.perf_counter() - start_time
    # t90 - t10 of a run that never reaches 10 % of the step is inf - inf: report inf.
    flat["rise_time"][np.isnan(flat["rise_time"])] = np.inf
    return flat, elapsed


def _result(flat, shape, axes, gains, settling_spec, overshoot_spec, dtype, elapsed):
    ts, os_, bad = flat["settling_time"], flat["overshoot"], flat["diverged"]
    feasible = ~bad & (ts < settling_spec) & (os_ < overshoot_spec)
    best, best_feasible = _best(flat, feasible, settling_spec, overshoot_spec)
    info = StepInfo(*(flat[name].reshape(shape) for name in StepInfo._fields))
    return GridResult(
        info=info,
        feasible=feasible.reshape(shape),
        best_index=tuple(int(i) for i in np.unravel_index(best, shape)),
        best_feasible=best_feasible,
        axes=axes,
        gains=gains,
        settling_spec=float(settling_spec),
        overshoot_spec=float(overshoot_spec),
        dtype=np.dtype(dtype).name,
        elapsed=float(elapsed),
    )


def _best(flat, feasible, settling_spec, overshoot_spec) -> tuple[int, bool]:
    """Flat index of the best point and whether it is feasible.

    Feasible: smallest settling time, ties (times are whole samples) broken by overshoot.
    None feasible: smallest relative violation max(0, ts/spec - 1) + max(0, os/spec - 1), ties
    (e.g. all never settle) broken by steady-state error, then overshoot; diverged runs last.
    """
    ts, os_ = flat["settling_time"], flat["overshoot"]
    if feasible.any():
        candidates = np.flatnonzero(feasible & (ts == ts[feasible].min()))
        return int(candidates[np.argmin(os_[candidates])]), True
    with np.errstate(invalid="ignore"):
        violation = np.maximum(0, ts / settling_spec - 1) + np.maximum(0, os_ / overshoot_spec - 1)
    violation = np.where(np.isnan(violation), np.inf, violation)
    pool = ~flat["diverged"] if not flat["diverged"].all() else np.ones_like(feasible)
    candidates = np.flatnonzero(pool & (violation == violation[pool].min()))
    order = np.lexsort((os_[candidates], flat["steady_state_error"][candidates]))
    return int(candidates[order[0]]), False


# ---------------------------------------------------------------- exact re-check


def recheck(plant, controller, experiment, gains) -> tuple[StepInfo, str]:
    """Metrics of one gain triple (kp, kd, ki) on the exact simulator, in float64.

    Returns (:class:`StepInfo`, a label naming the simulator)."""
    from jaxcart.exact import step_info_exact

    pid = dataclasses.replace(
        controller, kp=float(gains[0]), kd=float(gains[1]), ki=float(gains[2])
    )
    return step_info_exact(plant, pid, experiment), "exact simulator"


def comparison(result: GridResult, exact: StepInfo, label: str = "exact") -> str:
    """Table of the best point's metrics: the grid's numbers beside the re-check's."""
    grid = result.best_info
    head = f"grid ({result.dtype})"
    lines = [f"  {'':<24}{head:>16}{label:>18}"]
    for name, unit in METRICS.items():
        title = f"{name.replace('_', ' ')} [{unit}]"
        lines.append(
            f"  {title:<24}{_num(getattr(grid, name)):>16}{_num(getattr(exact, name)):>18}"
        )
    meets = (
        grid.meets(result.settling_spec, result.overshoot_spec),
        exact.meets(result.settling_spec, result.overshoot_spec),
    )
    lines.append(f"  {'meets specification':<24}{_yes(meets[0]):>16}{_yes(meets[1]):>18}")
    return "\n".join(lines)


def _num(x) -> str:
    return f"{x:.6g}" if np.isfinite(x) else "inf"


def _yes(b) -> str:
    return "yes" if b else "no"


def edge_notes(result: GridResult) -> list[str]:
    """Notes for each gain of the best point that sits on the boundary of its grid axis (the
    optimum may lie outside the grid); a lower bound of 0 is a physical one and is not noted."""
    if result.axes is None:
        return []
    notes = []
    for name, axis, i in zip(GAIN_UNITS, result.axes, result.best_index, strict=True):
        if axis.size > 1 and i == axis.size - 1:
            notes.append(f"{name} is at the upper end of its range ({axis[i]:.6g}); widen it")
        elif axis.size > 1 and i == 0 and axis[0] > 0:
            notes.append(f"{name} is at the lower end of its range ({axis[i]:.6g}); widen it")
    return notes


def describe_gains(gains) -> str:
    """'kp = 95.2 V/m, kd = 8.1 V s/m, ki = 0 V/(m s)'."""
    return ", ".join(
        f"{name} = {g:.6g} {unit}"
        for (name, unit), g in zip(GAIN_UNITS.items(), gains, strict=True)
    )


# ---------------------------------------------------------------- files


def save_npz(result: GridResult, path, *, exact: StepInfo | None = None, force=False):
    """Write the metric arrays to ``path`` (.npz); refuses to overwrite unless ``force``.

    Arrays: kp, kd, ki (grid axes) or gains (list, (B, 3)); each metric of :data:`METRICS`
    and diverged, feasible (shaped like the grid); best_index, best_gains, best_feasible;
    settling_spec [s], overshoot_spec [%], dtype, units (JSON of the units); and exact_<metric>
    of the best point's re-check when ``exact`` is given.
    """
    import json

    arrays = {}
    if result.axes is not None:
        arrays.update(kp=result.axes[0], kd=result.axes[1], ki=result.axes[2])
    else:
        arrays["gains"] = result.gains
    arrays.update({name: getattr(result.info, name) for name in StepInfo._fields})
    arrays.update(
        feasible=result.feasible,
        best_index=np.asarray(result.best_index),
        best_gains=np.asarray(result.best_gains),
        best_feasible=np.asarray(result.best_feasible),
        settling_spec=np.asarray(result.settling_spec),
        overshoot_spec=np.asarray(result.overshoot_spec),
        dtype=np.asarray(result.dtype),
        units=np.asarray(json.dumps({**GAIN_UNITS, **METRICS})),
    )
    if exact is not None:
        arrays.update({f"exact_{name}": np.asarray(v) for name, v in exact._asdict().items()})
    with _open(path, force) as f:
        np.savez(f, **arrays)
    return path


def _open(path, force):
    try:
        return open(path, "wb" if force else "xb")
    except FileExistsError:
        raise UserError(
            f"{path} exists; pass --force to overwrite it or choose another name"
        ) from None
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror}") from None


# ---------------------------------------------------------------- plots


def plot_slices(result: GridResult, path=None, *, n_slices: int = 4, force=False):
    """Heat maps of settling time [s] over kp x kd at a few ki slices; returns the figure.

    Feasible points are coloured by settling time; the infeasible region is hatched grey; the
    best point is marked with a star in its ki slice (that slice is always shown). A list of
    gains (no axes) is drawn as a kp-kd scatter instead. Saved as PNG to ``path`` when given
    (refuses to overwrite unless ``force``).
    """
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Rectangle

    if result.axes is None:
        fig = _plot_list(result)
    else:
        kp, kd, ki = result.axes
        per_slice = result.feasible.sum(axis=(0, 1))
        # Spread the slices over the ki range that has feasible points (all of it if none).
        span = int(np.flatnonzero(per_slice).max()) + 1 if per_slice.any() else ki.size
        slices = _slices(span, result.best_index[2], n_slices)
        ncols = min(len(slices), 2 if len(slices) == 4 else 3)
        nrows = -(-len(slices) // ncols)
        fig, axs = plt.subplots(
            nrows,
            ncols,
            figsize=(4.6 * ncols + 1.2, 3.9 * nrows),
            squeeze=False,
            sharex=True,
            sharey=True,
            layout="constrained",
        )
        shown = result.feasible if result.best_feasible else np.isfinite(result.info.settling_time)
        values = np.where(shown, result.info.settling_time, np.nan)
        lo = np.nanmin(values) if np.any(shown) else 0.0
        hi = result.settling_spec if result.best_feasible else np.nanmax(values, initial=1.0)
        mesh = None
        for ax, k in zip(axs.flat, slices, strict=False):
            ax.add_patch(
                Rectangle(
                    (0, 0),
                    1,
                    1,
                    transform=ax.transAxes,
                    facecolor="0.92",
                    edgecolor="0.6",
                    hatch="///",
                    linewidth=0,
                    zorder=0,
                )
            )
            z = np.ma.masked_invalid(values[:, :, k].T)
            mesh = ax.pcolormesh(
                _edges(kp),
                _edges(kd),
                z,
                cmap="viridis",
                vmin=lo,
                vmax=max(hi, lo + 1e-3),
                zorder=1,
            )
            if k == result.best_index[2]:
                b = result.best_gains
                ax.plot(
                    b[0],
                    b[1],
                    marker="*",
                    markersize=16,
                    color="red",
                    markeredgecolor="white",
                    linestyle="none",
                    zorder=3,
                )
            ax.set_title(f"$k_i$ = {ki[k]:.4g} V/(m s): {per_slice[k]} feasible")
        for ax in axs.flat[len(slices) :]:
            ax.set_visible(False)
        for ax in axs[-1]:
            ax.set_xlabel("$k_p$ [V/m]")
        for ax in axs[:, 0]:
            ax.set_ylabel("$k_d$ [V s/m]")
        what = "feasible points" if result.best_feasible else "all points (none feasible)"
        fig.colorbar(mesh, ax=axs, label=f"settling time [s], {what}")
        handles = [
            Patch(
                facecolor="0.92",
                edgecolor="0.6",
                hatch="///",
                label=_infeasible(result) if result.best_feasible else "does not settle in time",
            ),
            plt.Line2D(
                [],
                [],
                marker="*",
                markersize=12,
                color="red",
                linestyle="none",
                label="best" if result.best_feasible else "closest to the spec",
            ),
        ]
        fig.legend(handles=handles, loc="outside lower center", ncols=2, frameon=False)
        fig.suptitle(_title(result))
    if path is not None:
        with _open(path, force) as f:
            fig.savefig(f, format="png", dpi=110)
    return fig


def _plot_list(result):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.8), layout="constrained")
    g, ok = result.gains, result.feasible
    ts = result.info.settling_time
    ax.scatter(g[~ok, 0], g[~ok, 1], marker="x", color="0.6", label=_infeasible(result))
    if ok.any():
        pts = ax.scatter(
            g[ok, 0],
            g[ok, 1],
            c=ts[ok],
            cmap="viridis",
            vmax=result.settling_spec,
            label="feasible",
        )
        fig.colorbar(pts, ax=ax, label="settling time [s]")
    b = result.best_gains
    ax.plot(
        b[0],
        b[1],
        marker="*",
        markersize=16,
        color="red",
        markeredgecolor="white",
        linestyle="none",
        label="best" if result.best_feasible else "closest to the spec",
    )
    ax.set_xlabel("$k_p$ [V/m]")
    ax.set_ylabel("$k_d$ [V s/m]")
    ax.set_title("each gain triple at its (kp, kd); ki not shown", fontsize="small")
    fig.legend(loc="outside lower center", ncols=3, fontsize="small", frameon=False)
    fig.suptitle(_title(result))
    return fig


def _title(result) -> str:
    b = result.best_gains
    info = result.best_info
    head = "best" if result.best_feasible else "no feasible point; closest"
    return (
        f"{result.n_feasible} of {result.n_points} points feasible; {head}: "
        f"$k_p$ = {b[0]:.4g}, $k_d$ = {b[1]:.4g}, $k_i$ = {b[2]:.4g}\n"
        f"settling time {info.settling_time:.4g} s, overshoot {info.overshoot:.3g} %"
    )


def _infeasible(result) -> str:
    return (
        f"infeasible (settling $\\geq$ {result.settling_spec:g} s "
        f"or overshoot $\\geq$ {result.overshoot_spec:g} %)"
    )


def _slices(n: int, best: int, count: int) -> list[int]:
    """``count`` evenly spaced indices of n, the one nearest ``best`` replaced by ``best``."""
    if n <= count:
        return list(range(n))
    picks = np.round(np.linspace(0, n - 1, count)).astype(int)
    if best < n:
        picks[np.argmin(np.abs(picks - best))] = best
    return sorted(set(picks.tolist()))


def _edges(axis: np.ndarray) -> np.ndarray:
    """Cell edges around the points of a sorted axis (pcolormesh)."""
    if axis.size == 1:
        half = max(abs(axis[0]) * 0.05, 0.5)
        return np.array([axis[0] - half, axis[0] + half])
    mid = (axis[1:] + axis[:-1]) / 2
    return np.concatenate([[2 * axis[0] - mid[0]], mid, [2 * axis[-1] - mid[-1]]])


def progress_line(label: str = "grid", stream=None):
    """A ``progress(done, total)`` that keeps one status line on stderr."""
    stream = stream or sys.stderr
    start = time.perf_counter()
    tty = stream.isatty()

    def report(done, total):
        rate = done / max(time.perf_counter() - start, 1e-9)
        text = f"{label}: {done}/{total} points ({100 * done / total:.0f} %), {rate:,.0f} points/s"
        end = "\n" if done >= total or not tty else ""
        print(("\r" if tty else "") + text, end=end, file=stream, flush=True)

    return report
