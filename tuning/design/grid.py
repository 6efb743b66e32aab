"""Batched evaluation of PID gain grids (or any list of gain triples).

Every point (kp, kd, ki) of a kp x kd x ki grid is simulated with the digital loop of the lab
(hard clip, the exact forms) and its step metrics are streamed out without storing the run:
settling time [s], overshoot [%], rise time [s], steady-state error [m], peak voltage [V], time
in saturation [s], and whether it meets the specification (settling < ``settling_time`` and
overshoot < ``overshoot``, not diverged: :meth:`jaxcart.StepInfo.meets`).

Memory stays bounded for any grid: the gains of a block of points are generated from the axes
when the block is evaluated (the (B, 3) gain array of the whole grid is never built), each block
goes through :func:`jaxcart.batch_metrics.step_metrics_batch` (chunked, sharded over every local
device) and is kept by :mod:`tuning.design.grid_blocks` (checkpoint files, the share of each process
of a distributed run, the streaming reduction). A grid of up to
:data:`tuning.design.grid_blocks.FULL_LIMIT` points also keeps its metric arrays (about 30 bytes per
point); a larger one keeps summaries. With a plant set (a list of plants) every metric is the worst
over the set.

>>> import numpy as np, jaxcart as jc
>>> res = grid_search(jc.handout_plant(), jc.PID(v_limit=6.0), jc.step(0.5, horizon=1.5),
...                   np.linspace(40, 80, 3), np.linspace(4, 8, 3), [0.0])
>>> res.info.settling_time.shape
(3, 3, 1)
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
import zipfile
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle

from hw.atomicio import atomic_open
from jaxcart.batch_metrics import default_chunk, step_metrics_batch
from jaxcart.chunked_sim import duration_text
from jaxcart.errors import UserError
from jaxcart.exact import step_info_exact
from jaxcart.metrics import StepInfo
from jaxcart.smooth_sim import EXACT_FORMS
from tuning.design import grid_blocks
from tuning.design.grid_blocks import feasible_mask

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
        error [m], peak voltage [V], diverged (bool); None for a grid too large to hold
        (:data:`tuning.design.grid_blocks.FULL_LIMIT`): :meth:`slices` and :func:`save_npz` read its
        blocks back from ``store``
    feasible: bool array of ``shape``, True where the point meets the specification (None
        with ``info``)
    best_index: index (into ``shape``) of the best feasible point (smallest settling time,
        ties broken by overshoot); when none is feasible, of the point closest to feasibility
    best_feasible: whether the best point is feasible (False: none is)
    axes: (kp [V/m], kd [V s/m], ki [V/(m s)]) 1-D axes of a grid; None for a list
    gains: (B, 3) rows (kp, kd, ki) of a list; None for a grid (see :meth:`gains_at`)
    settling_spec: settling time bound [s]; overshoot_spec: overshoot bound [%]
    dtype: the floating type of the evaluation ("float32" or "float64")
    elapsed: wall time of the evaluation [s] (compilation included)
    grid_shape: the shape of the metric arrays; feasible_count: feasible points
    best: :class:`StepInfo` (Python scalars) of the best point
    ki_feasible: feasible points in each k_i slice (grids)
    settling_range: (min, max) finite settling time of any point [s] (nan, nan if none)
    n_plants: plants of the set the metrics are the worst over (1: one plant)
    store: the :class:`tuning.design.grid_blocks.BlockStore` of the blocks; block: points per block
    n_computed: points this process computed in this call (fewer when it resumed from a
        checkpoint or shared the work with other processes)
    """

    info: StepInfo | None
    feasible: np.ndarray | None
    best_index: tuple[int, ...]
    best_feasible: bool
    axes: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    gains: np.ndarray | None
    settling_spec: float
    overshoot_spec: float
    dtype: str
    elapsed: float
    grid_shape: tuple[int, ...] = ()
    feasible_count: int = 0
    best: StepInfo | None = None
    ki_feasible: np.ndarray | None = None
    settling_range: tuple[float, float] = (float("nan"), float("nan"))
    n_plants: int = 1
    store: object = None
    block: int = grid_blocks.BLOCK
    n_computed: int = 0

    @property
    def shape(self) -> tuple[int, ...]:
        return self.grid_shape

    @property
    def n_points(self) -> int:
        return int(np.prod(self.grid_shape))

    @property
    def n_feasible(self) -> int:
        return self.feasible_count

    @property
    def points_per_second(self) -> float:
        """Points this process computed per second of :attr:`elapsed`."""
        return self.n_computed / self.elapsed if self.elapsed > 0 else float("inf")

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
        return self.best

    def slices(self, ks) -> tuple[np.ndarray, np.ndarray]:
        """(settling time [s], feasible) of the k_i slices ``ks`` of a grid, each shaped
        (nkp, nkd, len(ks)); read from the blocks when the grid keeps no full arrays."""
        ks = [int(k) for k in ks]
        if self.info is not None:
            return self.info.settling_time[:, :, ks], self.feasible[:, :, ks]
        nkp, nkd, nki = self.grid_shape
        where = np.full(nki, -1)
        where[ks] = np.arange(len(ks))
        ts = np.full((nkp * nkd, len(ks)), np.nan)
        ok = np.zeros((nkp * nkd, len(ks)), bool)
        needs = ("settling_time", "overshoot", "diverged")
        for start, flat in grid_blocks.blocks(self.store, self.n_points, self.block, needs):
            idx = start + np.arange(flat["settling_time"].size)
            col = where[idx % nki]
            pick = col >= 0
            ts[idx[pick] // nki, col[pick]] = flat["settling_time"][pick]
            ok[idx[pick] // nki, col[pick]] = feasible_mask(
                flat, self.settling_spec, self.overshoot_spec
            )[pick]
        return ts.reshape(nkp, nkd, -1), ok.reshape(nkp, nkd, -1)


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
    chunk: int | None = None,
    progress=None,
    checkpoint=None,
    keep_full: bool | None = None,
    block: int = grid_blocks.BLOCK,
    say=None,
) -> GridResult | None:
    """Evaluate every point of the grid kp x kd x ki (1-D axes [V/m], [V s/m], [V/(m s)]).

    plant (or a list of plants: every metric is then the worst over the set), controller (its
    other settings: tau, v_limit, ...), experiment: a closed-loop step, as for
    :func:`jaxcart.simulate`. settling_time [s], overshoot [%]: the specification.
    dtype: ``jnp.float32`` (default, fast) or ``jnp.float64``; the evaluation runs in exactly
    that precision whatever ``jax_enable_x64`` says. smoothing: default the exact forms (hard
    clip), right for plants without friction. ``progress(done, total)`` after each block.
    checkpoint: a folder for the block files (a rerun of the same problem resumes from them;
    ``say(text)`` is told so); keep_full: hold every metric array (default: when the grid has at
    most :data:`tuning.design.grid_blocks.FULL_LIMIT` points). Metric arrays are shaped (len(kp),
    len(kd), len(ki)). In a distributed run (:func:`jaxcart.parallel.init_distributed`) every
    process
    computes its share of the blocks; process 0 returns the result, the others None.
    """
    _check_spec(settling_time, overshoot)
    axes = tuple(_axis(name, a) for name, a in (("kp", kp), ("kd", kd), ("ki", ki)))
    shape = tuple(a.size for a in axes)

    def rows(start, stop):
        i, j, k = np.unravel_index(np.arange(start, stop), shape)
        return np.stack([axes[0][i], axes[1][j], axes[2][k]], axis=1)

    return _evaluate(
        plant,
        controller,
        experiment,
        shape,
        rows,
        axes=axes,
        gains=None,
        spec=(settling_time, overshoot),
        dtype=dtype,
        smoothing=smoothing,
        chunk=chunk,
        progress=progress,
        checkpoint=checkpoint,
        keep_full=keep_full,
        block=block,
        say=say,
    )


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
    chunk: int | None = None,
    progress=None,
    checkpoint=None,
    block: int = grid_blocks.BLOCK,
    say=None,
) -> GridResult | None:
    """Evaluate each row (kp [V/m], kd [V s/m], ki [V/(m s)]) of ``gains`` (shape (B, 3)).

    Same options as :func:`grid_search`; the metric arrays are shaped (B,) and always kept.
    """
    _check_spec(settling_time, overshoot)
    gains = np.asarray(gains, dtype=float)
    if gains.ndim != 2 or gains.shape[1] != 3 or gains.shape[0] < 1:
        raise UserError(f"gains must have shape (B, 3) with rows (kp, kd, ki); got {gains.shape}")
    if not np.all(np.isfinite(gains)):
        raise UserError("gains contain a value that is not finite; give finite numbers")
    return _evaluate(
        plant,
        controller,
        experiment,
        gains.shape[:1],
        lambda start, stop: gains[start:stop],
        axes=None,
        gains=gains,
        spec=(settling_time, overshoot),
        dtype=dtype,
        smoothing=smoothing,
        chunk=chunk,
        progress=progress,
        checkpoint=checkpoint,
        keep_full=True,
        block=block,
        say=say,
    )


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


def _evaluate(
    plant,
    controller,
    experiment,
    shape,
    rows,
    *,
    axes,
    gains,
    spec,
    dtype,
    smoothing,
    chunk,
    progress,
    checkpoint,
    keep_full,
    block,
    say,
):
    """Metrics of the points whose gains ``rows(start, stop)`` gives, block by block."""
    plants, dtype = _checked_problem(plant, experiment, smoothing, dtype)
    n = int(np.prod(shape))
    # Same block size on every call (the last one padded) so the evaluator compiles once.
    block = int(min(n, block))
    keep_full = n <= grid_blocks.FULL_LIMIT if keep_full is None else bool(keep_full)
    where = plants if len(plants) > 1 else plants[0]
    # The chunk is not part of the problem: it moves a metric by rounding at most, and the
    # processes of one distributed run (a GPU host beside CPU hosts) may choose different ones.
    key = grid_blocks.problem_key(
        where,
        controller,
        experiment,
        smoothing,
        dtype.name,
        block,
        axes if axes is not None else gains,
    )
    store = _store(checkpoint, keep_full, key)
    compute = _block_metrics(
        where,
        controller,
        experiment,
        rows,
        n,
        block,
        smoothing,
        int(chunk or default_chunk()),
        dtype,
    )
    start_time = time.perf_counter()
    # Exactly the requested precision whatever jax_enable_x64 says globally: float64 needs it
    # on (the command line runs with it off); float32 must not pick up the default float64.
    with jax.enable_x64(dtype == np.float64):
        first, computed = grid_blocks.fill(store, n, block, compute, progress=progress, say=say)
        if not first:
            return None  # another process of a distributed run: process 0 reports
    elapsed = time.perf_counter() - start_time
    reducer = grid_blocks.Reducer(
        n, dtype, *spec, keep_full=keep_full, nki=shape[2] if axes is not None else None
    )
    for start, flat in grid_blocks.blocks(store, n, block):
        reducer.add(start, flat)
    if reducer.full is not None and store.dir is None:
        store.remove()  # the full arrays hold it all: no second copy in memory
    return _result(
        reducer,
        shape,
        axes=axes,
        gains=gains,
        spec=spec,
        dtype=dtype,
        elapsed=elapsed,
        n_plants=len(plants),
        store=store,
        block=block,
        computed=computed,
    )


def _checked_problem(plant, experiment, smoothing, dtype) -> tuple[list, np.dtype]:
    """(the plants as a list, dtype as a numpy dtype), or a UserError saying what to change."""
    if experiment.kind != "closed_loop":
        raise UserError(f"a gain grid needs a closed-loop step experiment, not {experiment.kind}")
    plants = list(plant) if isinstance(plant, list | tuple) else [plant]
    if not plants:
        raise UserError("the plant set is empty; give at least one plant")
    if any(e.stage == "force" for e in plants[0].effects) and smoothing == EXACT_FORMS:
        raise UserError(
            "the exact (hard) forms are for saturation only; with friction in the plant pass a "
            "smoothing (jaxcart.Smoothing) to the grid"
        )
    dtype = np.dtype(dtype)
    if dtype not in (np.float32, np.float64):
        raise UserError(f"dtype {dtype}: use float32 or float64")
    return plants, dtype


def _store(checkpoint, keep_full: bool, key: str) -> grid_blocks.BlockStore:
    """Block files in ``checkpoint``, else memory when the full arrays are kept anyway, else a
    temporary folder."""
    if checkpoint is not None:
        return grid_blocks.BlockStore(checkpoint, key)
    if keep_full:
        return grid_blocks.BlockStore(None, key)
    return grid_blocks.temporary_store(key)


def _block_metrics(where, controller, experiment, rows, n, block, smoothing, chunk, dtype):
    """compute(i) -> {name: array} of block i's points (the last block padded to ``block``
    points for the evaluation, then cut back)."""

    def compute(i):
        start, stop = i * block, min(n, (i + 1) * block)
        g = rows(start, stop)
        if stop - start < block:
            g = np.concatenate([g, np.repeat(g[-1:], block - (stop - start), 0)])
        info = step_metrics_batch(
            where, controller, experiment, g, smoothing=smoothing, chunk=chunk, dtype=dtype.type
        )
        flat = {k: np.asarray(v)[: stop - start] for k, v in info._asdict().items()}
        # t90 - t10 of a run that never reaches 10 % of the step is inf - inf: report inf.
        flat["rise_time"][np.isnan(flat["rise_time"])] = np.inf
        return flat

    return compute


def _result(reducer, shape, *, axes, gains, spec, dtype, elapsed, n_plants, store, block, computed):
    """The :class:`GridResult` of the reduced blocks."""
    best, best_feasible, best_values = reducer.best()
    full = reducer.full
    lo, hi = reducer.finite
    return GridResult(
        info=None
        if full is None
        else StepInfo(*(full[k].reshape(shape) for k in StepInfo._fields)),
        feasible=None if full is None else full["feasible"].reshape(shape),
        best_index=tuple(int(i) for i in np.unravel_index(best, shape)),
        best_feasible=best_feasible,
        axes=axes,
        gains=gains,
        settling_spec=float(spec[0]),
        overshoot_spec=float(spec[1]),
        dtype=dtype.name,
        elapsed=float(elapsed),
        grid_shape=tuple(shape),
        feasible_count=reducer.n_feasible,
        best=StepInfo(**{k: best_values[k] for k in StepInfo._fields}),
        ki_feasible=reducer.ki_feasible if axes is not None else None,
        settling_range=(lo, hi) if lo <= hi else (float("nan"), float("nan")),
        n_plants=n_plants,
        store=store,
        block=block,
        n_computed=computed,
    )


# ---------------------------------------------------------------- exact re-check


def recheck(plant, controller, experiment, gains) -> tuple[StepInfo, str]:
    """Metrics of one gain triple (kp, kd, ki) on the exact simulator, in float64.

    Returns (:class:`StepInfo`, a label naming the simulator)."""
    pid = dataclasses.replace(
        controller, kp=float(gains[0]), kd=float(gains[1]), ki=float(gains[2])
    )
    return step_info_exact(plant, pid, experiment), "exact simulator"


def recheck_set(plants, controller, experiment, gains) -> tuple[StepInfo, str]:
    """:func:`recheck` on every plant of a set: the field-wise worst (largest value, diverged
    if any) and a label naming the simulator and the number of plants."""
    plants = list(plants) if isinstance(plants, list | tuple) else [plants]
    infos = [recheck(p, controller, experiment, gains)[0] for p in plants]
    if len(infos) == 1:
        return infos[0], "exact simulator"
    worst = StepInfo(
        **{
            k: any(v) if k == "diverged" else float(np.max(v))
            for k, v in zip(StepInfo._fields, zip(*infos, strict=True), strict=True)
        }
    )
    return worst, f"exact, worst of {len(infos)}"


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


def summary(result: GridResult, exact: StepInfo | None = None) -> dict:
    """The result as JSON-ready data: grid, best point (gains, metrics, the exact re-check),
    feasible count and ``on_edge``: the notes of :func:`edge_notes` (empty: not on a bound)."""

    digits = 7 if result.dtype == "float32" else 17  # no float32 noise digits in the file

    def metrics(info):
        return {
            f"{name} [{unit}]": (float(f"{v:.{digits}g}") if np.isfinite(v) else None)
            for name, unit in METRICS.items()
            for v in [float(getattr(info, name))]
        } | {"diverged": bool(info.diverged)}

    doc = {
        "shape": list(result.shape),
        "n_points": result.n_points,
        "n_feasible": result.n_feasible,
        "n_plants": result.n_plants,
        "dtype": result.dtype,
        "spec": {"settling_time [s]": result.settling_spec, "overshoot [%]": result.overshoot_spec},
        "best_feasible": result.best_feasible,
        "best_gains": dict(zip(GAIN_UNITS, result.best_gains, strict=True)),
        "gain_units": GAIN_UNITS,
        "best_metrics": metrics(result.best_info),
        "on_edge": edge_notes(result),
    }
    if result.axes is not None:
        doc["axes"] = {
            name: {"lo": float(a[0]), "hi": float(a[-1]), "n": int(a.size)}
            for name, a in zip(GAIN_UNITS, result.axes, strict=True)
        }
    if exact is not None:
        doc["exact_metrics"] = metrics(exact)
    return doc


def save_json(result: GridResult, path, *, exact: StepInfo | None = None, force=False):
    """Write :func:`summary` to ``path``; refuses to overwrite unless ``force``."""
    with _open(path, force) as f:
        f.write((json.dumps(summary(result, exact), indent=2) + "\n").encode())
    return path


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
    on_edge (JSON list of the notes of :func:`edge_notes`: the best point on a bound of its
    range); n_plants (the metrics are the worst over that many plants); settling_spec [s],
    overshoot_spec [%], dtype, units (JSON of the units); and exact_<metric> of the best
    point's re-check when ``exact`` is given. A grid without full arrays is written block by
    block from its store (memory stays bounded).
    """
    small = {}
    if result.axes is not None:
        small.update(kp=result.axes[0], kd=result.axes[1], ki=result.axes[2])
    else:
        small["gains"] = result.gains
    small.update(
        best_index=np.asarray(result.best_index),
        best_gains=np.asarray(result.best_gains),
        best_feasible=np.asarray(result.best_feasible),
        on_edge=np.asarray(json.dumps(edge_notes(result))),
        n_plants=np.asarray(result.n_plants),
        settling_spec=np.asarray(result.settling_spec),
        overshoot_spec=np.asarray(result.overshoot_spec),
        dtype=np.asarray(result.dtype),
        units=np.asarray(json.dumps({**GAIN_UNITS, **METRICS})),
    )
    if exact is not None:
        small.update({f"exact_{name}": np.asarray(v) for name, v in exact._asdict().items()})
    names = (*StepInfo._fields, "feasible")
    with _open(path, force) as f, zipfile.ZipFile(f, "w", allowZip64=True) as zf:
        if result.info is not None:
            full = {**result.info._asdict(), "feasible": result.feasible}
            for name in names:
                _write_member(zf, name, full[name])
        else:
            for name in names:
                _stream_member(zf, name, result)
        for name, value in small.items():
            _write_member(zf, name, value)
    return path


def _write_member(zf, name, array) -> None:
    with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
        np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def _stream_member(zf, name, result) -> None:
    """One metric of every block, in order, as one .npy member shaped like the grid."""
    dtype = np.dtype(bool if name in ("diverged", "feasible") else result.dtype)
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False}
    header["shape"] = tuple(result.shape)
    with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
        np.lib.format.write_array_header_2_0(member, header)
        needs = ("settling_time", "overshoot", "diverged") if name == "feasible" else (name,)
        for _start, flat in grid_blocks.blocks(result.store, result.n_points, result.block, needs):
            if name == "feasible":
                values = feasible_mask(flat, result.settling_spec, result.overshoot_spec)
            else:
                values = flat[name]
            member.write(np.ascontiguousarray(values, dtype=dtype).tobytes())


def _open(path, force):
    """The output file under a temporary name, renamed when the block ends
    (:mod:`hw.atomicio`): a full disk leaves no half file; an existing file is refused
    unless ``force``."""
    return atomic_open(path, "wb", force=force)


# ---------------------------------------------------------------- plots


def plot_slices(result: GridResult, path=None, *, n_slices: int = 4, force=False):
    """Heat maps of settling time [s] over kp x kd at a few ki slices; returns the figure.

    Feasible points are coloured by settling time; the infeasible region is hatched grey; the
    best point is marked with a star in its ki slice (that slice is always shown). A list of
    gains (no axes) is drawn as a kp-kd scatter instead. Saved to ``path`` when given, as
    PNG, SVG or PDF by its suffix (PNG for any other; refuses to overwrite unless ``force``).
    """
    fig = _plot_list(result) if result.axes is None else _plot_grid(result, n_slices)
    if path is not None:
        suffix = os.path.splitext(str(path))[1].lower().lstrip(".")
        with _open(path, force) as f:
            fig.savefig(f, format=suffix if suffix in ("svg", "pdf") else "png", dpi=110)
    return fig


def _plot_grid(result: GridResult, n_slices: int):
    """The heat maps of :func:`plot_slices` for a grid."""
    ki = result.axes[2]
    per_slice = result.ki_feasible
    # Spread the slices over the ki range that has feasible points (all of it if none).
    span = int(np.flatnonzero(per_slice).max()) + 1 if per_slice.any() else ki.size
    slices = _slices(span, result.best_index[2], n_slices)
    ncols = min(len(slices), 2 if len(slices) == 4 else 3)
    nrows = -(-len(slices) // ncols)
    fig = Figure(figsize=(4.6 * ncols + 1.2, 3.9 * nrows), layout="constrained")
    axs = fig.subplots(nrows, ncols, squeeze=False, sharex=True, sharey=True)
    settling, ok = result.slices(slices)
    shown = ok if result.best_feasible else np.isfinite(settling)
    values = np.where(shown, settling, np.nan)
    limits = _colour_limits(result)
    mesh = None
    for col, (ax, k) in enumerate(zip(axs.flat, slices, strict=False)):
        mesh = _draw_slice(ax, result, k, values[:, :, col], limits)
    for ax in axs.flat[len(slices) :]:
        ax.set_visible(False)
    for ax in axs[-1]:
        ax.set_xlabel("$k_p$ [V/m]")
    for ax in axs[:, 0]:
        ax.set_ylabel("$k_d$ [V s/m]")
    what = "feasible points" if result.best_feasible else "all points (none feasible)"
    fig.colorbar(mesh, ax=axs, label=f"settling time [s], {what}")
    fig.legend(handles=_grid_legend(result), loc="outside lower center", ncols=2, frameon=False)
    fig.suptitle(_title(result) + "\n" + slice_note(result, slices))
    return fig


def _colour_limits(result: GridResult) -> tuple[float, float]:
    """(low, high) settling time [s] of the colour scale: from the best to the bound, or the
    range of the settling times when none is feasible."""
    if result.best_feasible:
        return result.best_info.settling_time, result.settling_spec
    if np.isfinite(result.settling_range[0]):
        return result.settling_range
    return 0.0, 1.0


def _draw_slice(ax, result: GridResult, k: int, values, limits):
    """One k_i slice ``k``: the hatched infeasible background, the settling times ``values``
    (kp x kd, nan where not shown) and the best point's star; returns the mesh."""
    kp, kd, ki = result.axes
    lo, hi = limits
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
    mesh = ax.pcolormesh(
        _edges(kp),
        _edges(kd),
        np.ma.masked_invalid(values.T),
        cmap="viridis",
        vmin=lo,
        vmax=max(hi, lo + 1e-3),
        zorder=1,
    )
    best = k == result.best_index[2]
    if best:
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
    ax.set_title(
        f"$k_i$ = {ki[k]:.4g} V/(m s) (slice {k + 1} of {ki.size}{', best' if best else ''}): "
        f"{result.ki_feasible[k]} feasible",
        fontsize="medium",
    )
    return mesh


def _grid_legend(result: GridResult) -> list:
    """The legend's handles: the hatched infeasible region and the best point's star."""
    return [
        Patch(
            facecolor="0.92",
            edgecolor="0.6",
            hatch="///",
            label=_infeasible(result) if result.best_feasible else "does not settle in time",
        ),
        Line2D(
            [],
            [],
            marker="*",
            markersize=12,
            color="red",
            linestyle="none",
            label="best" if result.best_feasible else "closest to the spec",
        ),
    ]


def slice_note(result: GridResult, slices) -> str:
    """Which k_i slices a figure shows (spread over the k_i range with feasible points, the
    best point's included), e.g. 'k_i slices shown: 4 of 64 (0, 9.5, 20, 30 V/(m s)), ...'."""
    ki = result.axes[2]
    if len(slices) == ki.size:
        return f"all {ki.size} $k_i$ slices shown"
    values = ", ".join(f"{ki[k]:.4g}" for k in slices)
    return f"$k_i$ slices shown: {len(slices)} of {ki.size} ({values} V/(m s)), with the best's"


def _plot_list(result):
    fig = Figure(figsize=(6.4, 4.8), layout="constrained")
    ax = fig.subplots()
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
    edge = [n.split(" is at the ")[0] for n in edge_notes(result)]
    edge = f" (on the range's bound: {', '.join(edge)})" if edge else ""
    where = f" (worst of {result.n_plants} plants)" if result.n_plants > 1 else ""
    return (
        f"{result.n_feasible} of {result.n_points} points feasible{where}; {head}: "
        f"$k_p$ = {b[0]:.4g}, $k_d$ = {b[1]:.4g}, $k_i$ = {b[2]:.4g}\n"
        f"settling time {info.settling_time:.4g} s, overshoot {info.overshoot:.3g} %{edge}"
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


def progress_line(label: str = "grid", stream=None, *, devices: str = ""):
    """A ``progress(done, total)`` that keeps one status line on stderr with the time left;
    after the second report (the first includes compilation) it prints, once, a cost estimate
    "about N min on <devices>" when the rest will take over a minute."""
    stream = stream or sys.stderr
    start = time.perf_counter()
    tty = stream.isatty()
    state = {"calls": 0, "first": None}

    def report(done, total):
        now = time.perf_counter()
        state["calls"] += 1
        if state["calls"] == 1:
            state["first"] = (now, done)
        rate = done / max(now - start, 1e-9)
        if state["calls"] >= 2:  # rate without the compilation
            t0, d0 = state["first"]
            rate = (done - d0) / max(now - t0, 1e-9)
        left = (total - done) / max(rate, 1e-9)
        if state["calls"] == 2 and left > 60:
            where = devices or "this machine"
            print(
                ("\n" if tty else "")
                + f"estimate: about {duration_text(now - start + left)} on {where} "
                f"({rate:,.0f} points/s)",
                file=stream,
                flush=True,
            )
        text = f"{label}: {done}/{total} points ({100 * done / total:.0f} %), {rate:,.0f} points/s"
        if done < total and state["calls"] >= 2:
            text += f", {duration_text(left)} left"
        end = "\n" if done >= total or not tty else ""
        print(("\r" if tty else "") + text, end=end, file=stream, flush=True)

    return report
