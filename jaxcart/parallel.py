"""The one device layer: which devices a batch runs on, one mesh, one sharded map.

Every batched computation in jaxcart (grid metrics, tuner starts, fit trial steps, diagnosis
candidates, bench rows) goes through :func:`sharded_map`, so it runs on every local device:
the CPU cores split into ``jax_num_cpu_devices`` devices (:func:`use_cpu_devices`, called by
the command line before JAX starts), or every local GPU.

``sharded_map(fn)`` returns a jitted function of ``(batch, *shared)``: ``fn(item, *shared)``
is vmapped over the leading axis of every leaf of ``batch`` (any pytree), in chunks of at
most ``chunk`` items per device (``lax.map`` over chunks bounds the working set), and the
chunks are sharded over the mesh. The batch is padded to a whole number of chunks and the
padding dropped again, so any batch size works. Compiled functions are cached by
``(fn, chunk, devices)``: pass the same ``fn`` object to reuse them.

>>> import jax.numpy as jnp
>>> square = sharded_map(lambda x, k: k * x**2)
>>> [float(v) for v in square(jnp.arange(5.0), 2.0)]
[0.0, 2.0, 8.0, 18.0, 32.0]
"""

from __future__ import annotations

import os
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

#: Name of the one mesh axis: the batch.
AXIS = "batch"


def use_cpu_devices(n: int | None = None) -> None:
    """Split the CPU into ``n`` XLA devices (default: one per core) so batches use every core.

    Must run before JAX starts a backend; later calls (or a user's own setting of
    ``jax_num_cpu_devices`` or ``--xla_force_host_platform_device_count``) win nothing and
    are left alone."""
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return
    n = n or os.cpu_count() or 1
    try:
        if jax.config.jax_num_cpu_devices in (-1, None):
            jax.config.update("jax_num_cpu_devices", int(n))
    except (AttributeError, RuntimeError):  # a backend already started, or an older JAX
        pass


def devices() -> list:
    """The devices this process computes on: every local GPU (or TPU), else the CPU devices."""
    return list(jax.local_devices())


_MESHES: dict = {}


def mesh(devs: list | None = None) -> Mesh:
    """The one-axis mesh (:data:`AXIS`) over ``devs`` (default :func:`devices`); cached."""
    devs = list(devs or devices())
    key = tuple(d.id for d in devs)
    if key not in _MESHES:
        _MESHES[key] = Mesh(np.array(devs), (AXIS,))
    return _MESHES[key]


def batch_sharding(m: Mesh | None = None) -> NamedSharding:
    """Leading axis split over the mesh."""
    return NamedSharding(m or mesh(), P(AXIS))


def replicated(m: Mesh | None = None) -> NamedSharding:
    """A copy on every device of the mesh."""
    return NamedSharding(m or mesh(), P())


def padded_size(n: int, chunk: int, n_dev: int) -> int:
    """Smallest multiple of ``chunk * n_dev`` that holds ``n`` items."""
    unit = chunk * n_dev
    return max(1, -(-n // unit)) * unit


def pad(batch, size: int):
    """Pad every leaf's leading axis to ``size`` by repeating its last item (a valid input)."""

    def leaf(a):
        a = jnp.asarray(a)
        extra = size - a.shape[0]
        if extra <= 0:
            return a
        return jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)])

    return jax.tree.map(leaf, batch)


def batch_size(batch) -> int:
    """Leading dimension shared by every leaf of ``batch``; a clear error otherwise."""
    sizes = {int(np.shape(a)[0]) if np.ndim(a) else -1 for a in jax.tree.leaves(batch)}
    if len(sizes) != 1 or -1 in sizes:
        raise ValueError(f"every leaf of a batch needs the same leading axis; got sizes {sizes}")
    return sizes.pop()


_COMPILED: dict = {}


def sharded_map(fn: Callable, *, chunk: int | None = None, devs: list | None = None) -> Callable:
    """``run(batch, *shared)``: ``vmap(fn)`` over ``batch``'s leading axis, sharded.

    ``chunk``: most items one device evaluates at once (default: the whole per-device share,
    i.e. a single vmap); smaller chunks bound memory, e.g. of a backward pass. ``shared``
    arguments are replicated. The result is a pytree of arrays with the batch's leading size.
    """
    devs = list(devs or devices())
    key = (fn, chunk, tuple(d.id for d in devs))
    if key in _COMPILED:
        return _COMPILED[key]
    m = mesh(devs)
    n_dev = len(devs)
    jitted: dict = {}

    def compiled(n_shared: int, step: int):
        if (n_shared, step) not in jitted:

            def local(batch, *shared):
                blocks = jax.tree.map(lambda a: a.reshape((-1, step) + a.shape[1:]), batch)
                out = jax.lax.map(lambda blk: jax.vmap(lambda x: fn(x, *shared))(blk), blocks)
                return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), out)

            jitted[n_shared, step] = jax.jit(
                jax.shard_map(
                    local,
                    mesh=m,
                    in_specs=(P(AXIS),) + (P(),) * n_shared,
                    out_specs=P(AXIS),
                    check_vma=False,
                )
            )
        return jitted[n_shared, step]

    def run(batch, *shared):
        n = batch_size(batch)
        per_device = -(-n // n_dev)
        step = min(chunk or per_device, per_device)
        size = padded_size(n, step, n_dev)
        padded = jax.device_put(pad(batch, size), batch_sharding(m))
        out = compiled(len(shared), step)(padded, *shared)
        return jax.tree.map(lambda a: a[:n], out)

    _COMPILED[key] = run
    return run


def map_blocks(
    fn: Callable,
    batch,
    *shared,
    chunk: int | None = None,
    block: int | None = None,
    progress: Callable[[int, int], None] | None = None,
):
    """:func:`sharded_map` over ``batch`` in host-side blocks of at most ``block`` items,
    returned as numpy arrays: memory stays bounded by the block whatever the batch size.
    ``progress(done, total)`` is called after each block."""
    run = sharded_map(fn, chunk=chunk)
    total = batch_size(batch)
    block = block or total
    pieces = []
    for start in range(0, total, block):
        part = jax.tree.map(lambda a, s=start: a[s : s + block], batch)
        pieces.append(jax.tree.map(np.asarray, run(part, *shared)))
        if progress is not None:
            progress(min(start + block, total), total)
    return jax.tree.map(lambda *xs: np.concatenate(xs), *pieces)


__all__ = [
    "AXIS",
    "batch_sharding",
    "batch_size",
    "devices",
    "map_blocks",
    "mesh",
    "pad",
    "padded_size",
    "replicated",
    "sharded_map",
    "use_cpu_devices",
]
