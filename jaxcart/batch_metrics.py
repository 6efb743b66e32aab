"""Many runs in one call: step metrics for a batch of gain triples, chunked so the working set
stays in cache, sharded over every local device by :func:`jaxcart.parallel.map_blocks`.

Devices come from :mod:`jaxcart.parallel` (on a CPU, :func:`jaxcart.parallel.use_cpu_devices`
splits the cores into devices before JAX starts, as the command line does).

>>> import numpy as np, jaxcart as jc
>>> gains = np.array([[40.0, 5.0, 0.0], [60.0, 6.0, 0.0]])
>>> info = step_metrics_batch(jc.handout_plant(), jc.PID(v_limit=6.0), jc.step(0.5), gains)
>>> info.overshoot.shape
(2,)
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxcart import parallel, xlaflags
from jaxcart.metrics import StepInfo, step_metrics
from jaxcart.smooth_sim import EXACT_FORMS

#: Runs per chunk where loops compile whole (a CPU backend, jaxcart.xlaflags in effect): the
#: loop's state in the L1 cache (W1 per CPU-second, 2 cores, float32 / float64 against 256
#: runs: 128 runs 0.97x / 1.03x, 512 runs 1.0x / 0.96x, 1024 runs 0.9x / 0.79x, measured).
KERNEL_CHUNK = 256
#: Runs per chunk otherwise (a GPU, or a CPU backend JAX started before jaxcart was imported,
#: whose loops run as one task per operation): 4096 lanes x ~10 state values fit in L2;
#: chunks of 1024, 2048 or 8192 ran 0.95-0.99x as fast (measured, 2 cores).
WIDE_CHUNK = 4096
#: Chunks per device in one host-side block: bounds the device working set of a large batch.
CHUNKS_PER_CALL = 64
#: XLA options of the batch program by backend (given per program: the tuner's own programs
#: do not get them). On a CPU, 512-bit vectors where the CPU has them (XLA prefers 256; a CPU
#: without AVX-512 is unaffected): W1 1.6x per CPU-second with loops compiled whole, 1.2-1.4x
#: without (measured, 2-core AVX-512 AMD EPYC), metrics bit for bit the same. Tried and not
#: kept: copy insertion by region analysis (1.10-1.15x without whole-loop kernels; with them
#: 1.0x, and a final position one rounding apart from the plain program's);
#: xla_cpu_enable_fast_min_max (max would stop propagating NaN, which marks a diverged run);
#: the concurrency-optimized or another scheduler, tiling propagation, backend optimization
#: level (0.9-1.05x); multi-output fusion (XLA_FLAGS only: 1.12x float32 but 0.85x float64).
COMPILER_OPTIONS = {"cpu": {"xla_cpu_prefer_vector_width": 512}}


def loops_whole() -> bool:
    """True when this process's default backend compiles jaxcart's chunked loops into one
    kernel each (:func:`jaxcart.xlaflags.loop_kernels` on a CPU)."""
    return jax.default_backend() == "cpu" and xlaflags.loop_kernels()


def default_chunk(kernel: int = KERNEL_CHUNK, wide: int = WIDE_CHUNK) -> int:
    """Runs per chunk on this process's default backend: ``kernel`` where loops compile whole
    (:func:`loops_whole`), ``wide`` otherwise."""
    return kernel if loops_whole() else wide


_FNS: dict = {}
#: The controller's numbers a row of gains may set, in order: the gains (kp, kd, ki), then the
#: derivative filter tau [s], the back-calculation gain kb [1/s] and the software limit v_limit
#: [V] (a row of 3 or of 6).
ROW_NAMES = ("kp", "kd", "ki", "tau", "kb", "v_limit")


def _metrics_fn(plant, base, experiment, smoothing, substeps, worst):
    """``fn(gains, plant, base, experiment)`` for one gain triple (``worst``: the field-wise
    worst over a stacked plant set); one object per static configuration, so
    :func:`jaxcart.parallel.sharded_map` reuses its compilation."""
    # Smoothing is baked in (not an argument): widths known to be 0 select the exact forms.
    widths = tuple(float(w) for w in jax.tree_util.tree_leaves(smoothing))
    key = (jax.tree_util.tree_structure((plant, base, experiment)), widths, substeps, worst)
    if key not in _FNS:

        def one(gains, plant, base, experiment):
            names = ROW_NAMES[: gains.shape[-1]]
            controller = dataclasses.replace(base, **{n: gains[i] for i, n in enumerate(names)})
            return step_metrics(
                plant, controller, experiment, smoothing=smoothing, substeps=substeps
            )

        def over_plants(gains, plants, base, experiment):
            info = jax.vmap(one, in_axes=(None, 0, None, None))(gains, plants, base, experiment)
            return StepInfo(
                *(jnp.any(v) if k == "diverged" else jnp.max(v) for k, v in info._asdict().items())
            )

        _FNS[key] = over_plants if worst else one
    return _FNS[key]


def stack_plants(plants):
    """One plant pytree whose leaves have a leading plant axis (the plants must share their
    effects); a clear error otherwise."""
    structures = {jax.tree_util.tree_structure(p) for p in plants}
    if len(structures) != 1:
        raise ValueError("a plant set must share its effects (one pytree structure)")
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *plants)


def step_metrics_batch(
    plant,
    controller,
    experiment,
    gains,
    *,
    smoothing=EXACT_FORMS,
    substeps=None,
    chunk: int | None = None,
    dtype=None,
    progress=None,
) -> StepInfo:
    """:class:`StepInfo` arrays for each row (kp, kd, ki) of ``gains`` (shape (B, 3)), or
    (kp, kd, ki, tau, kb, v_limit) (shape (B, 6), :data:`ROW_NAMES`).

    ``plant``: one plant, or a list of plants (a plant set): then every metric is the worst
    over the set (the largest value; diverged if any diverged). The other controller settings
    come from ``controller``. Default ``smoothing`` is the
    exact forms (hard clip): the grid reports what the real loop would do. ``dtype`` casts the
    computation (``jnp.float32`` for speed). ``chunk``: runs per device at a time (default
    :func:`default_chunk`). Memory is bounded: gains are processed in blocks of at most 64
    chunks per device. ``progress(done, total)`` is called after each. No rows (B = 0): empty
    arrays of each field's dtype, nothing run.
    """
    gains = np.asarray(gains)
    if gains.ndim != 2 or gains.shape[1] not in (3, len(ROW_NAMES)):
        raise ValueError(
            f"gains must have shape (B, 3) for (kp, kd, ki) or (B, 6) for "
            f"{', '.join(ROW_NAMES)}; got {gains.shape}"
        )
    chunk = parallel.positive(chunk, "step_metrics_batch: chunk")
    dtype = jnp.dtype(dtype or jnp.result_type(float))
    # float64 needs x64 on; enable it here rather than silently computing in float32.
    with jax.enable_x64(dtype == jnp.float64 or bool(jax.config.jax_enable_x64)):
        cast = _caster(dtype)
        worst = isinstance(plant, list | tuple)
        plant = stack_plants([cast(p) for p in plant]) if worst else cast(plant)
        controller, experiment = cast(controller), cast(experiment)
        n_dev = len(parallel.devices())
        total = gains.shape[0]
        # One chunk size for every block of this batch (the last block is padded to it).
        chunk = int(min(chunk or default_chunk(), max(8, -(-total // n_dev))))
        fn = _metrics_fn(plant, controller, experiment, smoothing, substeps, worst)
        out = parallel.map_blocks(
            fn,
            gains.astype(dtype),
            plant,
            controller,
            experiment,
            chunk=chunk,
            block=chunk * n_dev * CHUNKS_PER_CALL,
            progress=progress,
            compiler_options=COMPILER_OPTIONS.get(jax.default_backend()),
        )
    return StepInfo(*out)


def _caster(dtype):
    def cast(tree):
        def leaf(x):
            if isinstance(x, bool | np.bool_) or (hasattr(x, "dtype") and x.dtype == bool):
                return x
            if isinstance(x, float | int) or jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating):
                return jnp.asarray(x, dtype=dtype)
            return x

        return jax.tree_util.tree_map(leaf, tree)

    return cast
