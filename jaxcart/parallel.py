"""The one device layer: which devices a batch runs on, one mesh, one sharded map.

Every batched computation in jaxcart runs on this module's mesh: grid metrics, fit trial
steps, diagnosis candidates and bench rows through :func:`sharded_map`, the tuner's starts
(whose optimizer state stays on the devices between iterations) through
:func:`batch_sharding`. So every local device is used:
the CPU cores split into ``jax_num_cpu_devices`` devices (:func:`use_cpu_devices`, called by
the command line before JAX starts), or every local GPU.

``sharded_map(fn)`` returns a jitted function of ``(batch, *shared)``: ``fn(item, *shared)``
is vmapped over the leading axis of every leaf of ``batch`` (any pytree), in chunks of at
most ``chunk`` items per device (``lax.map`` over chunks bounds the working set), and the
chunks are sharded over the mesh. The batch is padded to a whole number of chunks and the
padding dropped again, so any batch size works. Compiled functions are cached by
``(fn, chunk, devices)``: pass the same ``fn`` object to reuse them.

Past one machine: :func:`cluster_settings` and :func:`init_distributed` join a
``jax.distributed`` run (options, JAXCART_* variables, or SLURM / Open MPI); each process
computes its :func:`partition` of the work on its own devices and :func:`publish` /
:func:`fetch` carry results to process 0 through the runtime's key-value store.

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
from jax._src import distributed as _dist
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxcart import aot
from jaxcart.errors import UserError

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
    return NamedSharding(m or mesh(), PartitionSpec(AXIS))


def replicated(m: Mesh | None = None) -> NamedSharding:
    """A copy on every device of the mesh."""
    return NamedSharding(m or mesh(), PartitionSpec())


def put(x, dtype=None, sharding=None):
    """``x`` as a device array without compiling anything: host values (numpy, Python numbers,
    lists) are converted on the host and transferred. ``jnp.asarray`` of a host value compiles
    a small program per shape and dtype (10-40 ms each in a new process), the fixed cost a
    short command pays many times over. dtype: as ``jnp.asarray`` takes it (``float`` is
    float64 under x64, float32 otherwise); a JAX array or tracer goes through ``jnp.asarray``.
    """
    if isinstance(x, jax.Array | jax.core.Tracer):
        x = x if dtype is None else jnp.asarray(x, dtype)
        return x if sharding is None else jax.device_put(x, sharding)
    if dtype is None and isinstance(x, bool | int | float | complex):
        return jax.device_put(x, sharding)  # weakly typed, like jnp.asarray of a scalar
    # device_put narrows float64 to float32 without x64, as jnp.asarray does.
    host = np.asarray(x) if dtype is None else np.asarray(x, jax.dtypes.canonicalize_dtype(dtype))
    return jax.device_put(host, sharding)


def padded_size(n: int, chunk: int, n_dev: int) -> int:
    """Smallest multiple of ``chunk * n_dev`` that holds ``n`` items (at least one unit)."""
    if chunk < 1 or n_dev < 1:
        raise ValueError(f"padded_size: chunk and n_dev must be >= 1; got {chunk}, {n_dev}")
    unit = chunk * n_dev
    return max(1, -(-n // unit)) * unit


def pad(batch, size: int):
    """Pad every leaf's leading axis to ``size`` by repeating its last item (a valid input).

    Host (numpy) leaves are padded on the host, so a large batch never lands on one device
    before it is split over the mesh."""

    def leaf(a):
        xp = np if isinstance(a, np.ndarray) else jnp
        a = xp.asarray(a)
        extra = size - a.shape[0]
        if extra <= 0:
            return a
        if a.shape[0] == 0:
            raise ValueError(f"cannot pad an empty batch to {size} items: no item to repeat")
        return xp.concatenate([a, xp.repeat(a[-1:], extra, axis=0)])

    return jax.tree.map(leaf, batch)


def batch_size(batch) -> int:
    """Leading dimension shared by every leaf of ``batch``; a clear error otherwise."""
    sizes = {int(np.shape(a)[0]) if np.ndim(a) else -1 for a in jax.tree.leaves(batch)}
    if len(sizes) != 1 or -1 in sizes:
        raise ValueError(f"every leaf of a batch needs the same leading axis; got sizes {sizes}")
    return sizes.pop()


def positive(value, what: str):
    """``value`` (None, or an int >= 1) or a clear ValueError."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"{what} = {value!r}: give a whole number >= 1 (or None)")
    return int(value)


def empty_result(fn: Callable, batch, *shared, whole_chunks: bool = False, host: bool = False):
    """What mapping ``fn`` over ``batch`` returns when the batch has no items: every leaf of
    ``fn``'s result with a leading axis of 0, its shape and dtype found by abstract evaluation
    (``jax.eval_shape``: ``fn`` is traced on one item's shapes, never run on data). numpy
    arrays with ``host``, else device arrays. A ValueError says so when ``fn`` cannot be
    traced on those shapes, so that its result's shapes cannot be known without data."""

    def spec(a):
        dtype = a.dtype if isinstance(a, jax.Array) else np.asarray(a).dtype
        one = (1,) if whole_chunks else ()  # a whole-chunk fn gets a chunk of one item
        return jax.ShapeDtypeStruct(
            one + tuple(np.shape(a)[1:]), jax.dtypes.canonicalize_dtype(dtype)
        )

    try:
        out = jax.eval_shape(fn, jax.tree.map(spec, batch), *shared)
    except Exception as exc:  # whatever fn raises while traced
        why = (str(exc).strip().splitlines() or [""])[0][:200]
        raise ValueError(
            f"an empty batch (0 items): the shapes of {getattr(fn, '__name__', 'fn')}'s "
            f"result cannot be known without data ({type(exc).__name__}: {why}); "
            "give at least one item"
        ) from exc

    def leaf(s):
        shape = (0,) + tuple(s.shape[1:] if whole_chunks else s.shape)
        zeros = np.zeros(shape, s.dtype)
        return zeros if host else jax.device_put(zeros)

    return jax.tree.map(leaf, out)


_COMPILED: dict = {}


def sharded_map(
    fn: Callable,
    *,
    chunk: int | None = None,
    devs: list | None = None,
    cache: bool = True,
    name: str | None = None,
    static=(),
    compiler_options: dict | None = None,
    whole_chunks: bool = False,
) -> Callable:
    """``run(batch, *shared)``: ``vmap(fn)`` over ``batch``'s leading axis, sharded.

    ``chunk``: most items one device evaluates at once (default: the whole per-device share,
    i.e. a single vmap); smaller chunks bound memory, e.g. of a backward pass. ``shared``
    arguments are replicated. The result is a pytree of arrays with the batch's leading size
    (an empty batch compiles nothing: :func:`empty_result` gives its shapes and dtypes).
    ``cache=False`` for a one-off ``fn`` (a closure over one problem's data): the caller keeps
    the returned function, and it is freed with it. ``name`` (with ``static``, a value whose
    ``repr`` names every setting ``fn`` closes over) keeps the traced programs on disk
    (:mod:`jaxcart.aot`), so a new process does not trace them again. ``compiler_options``:
    XLA options of the compiled program (plain jit only), e.g.
    ``{"xla_cpu_prefer_vector_width": 512}``. ``whole_chunks``: ``fn(chunk, *shared)`` takes
    a whole chunk (every leaf with the chunk's leading axis) and maps it itself.
    """
    chunk = positive(chunk, "sharded_map: chunk")
    devs = list(devs or devices())
    options = tuple(sorted((compiler_options or {}).items()))
    if options and name is not None:
        raise ValueError("sharded_map: compiler_options need name=None (plain jit)")
    key = (fn, chunk, tuple(d.id for d in devs), options, name, static, whole_chunks)
    if cache and key in _COMPILED:
        return _COMPILED[key]
    m = mesh(devs)
    n_dev = len(devs)
    jitted: dict = {}

    def compiled(n_shared: int, step: int):
        if (n_shared, step) not in jitted:

            def local(batch, *shared):
                blocks = jax.tree.map(lambda a: a.reshape((-1, step) + a.shape[1:]), batch)

                def one_chunk(blk):
                    if whole_chunks:
                        return fn(blk, *shared)
                    return jax.vmap(lambda x: fn(x, *shared))(blk)

                out = jax.lax.map(one_chunk, blocks)
                return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), out)

            mapped = jax.shard_map(
                local,
                mesh=m,
                in_specs=(PartitionSpec(AXIS),) + (PartitionSpec(),) * n_shared,
                out_specs=PartitionSpec(AXIS),
                check_vma=False,
            )
            if name is None:
                jitted[n_shared, step] = jax.jit(mapped, compiler_options=dict(options) or None)
            else:
                jitted[n_shared, step] = aot.jit(mapped, name, (static, n_shared, step, n_dev))
        return jitted[n_shared, step]

    def run(batch, *shared):
        n = batch_size(batch)
        if n == 0:
            return empty_result(fn, batch, *shared, whole_chunks=whole_chunks)
        per_device = -(-n // n_dev)
        step = min(chunk or per_device, per_device)
        size = padded_size(n, step, n_dev)
        padded = jax.device_put(pad(batch, size), batch_sharding(m))
        out = compiled(len(shared), step)(padded, *shared)
        return jax.tree.map(lambda a: a[:n], out)

    if cache:
        _COMPILED[key] = run
    return run


def map_blocks(
    fn: Callable,
    batch,
    *shared,
    chunk: int | None = None,
    block: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    compiler_options: dict | None = None,
):
    """:func:`sharded_map` over ``batch`` in host-side blocks of at most ``block`` items,
    returned as numpy arrays: memory stays bounded by the block whatever the batch size.
    A short last block is padded to the full block, so every block runs one compiled program.
    ``progress(done, total)`` is called after each block. An empty batch (0 items) runs no
    block and returns empty arrays of the shapes and dtypes ``fn`` gives (:func:`empty_result`).
    """
    block = positive(block, "map_blocks: block")
    run = sharded_map(fn, chunk=chunk, compiler_options=compiler_options)
    total = batch_size(batch)
    if total == 0:
        return empty_result(fn, batch, *shared, host=True)
    block = min(block or total, total)
    pieces = []
    for start in range(0, total, block):
        part = jax.tree.map(lambda a, s=start: a[s : s + block], batch)
        n = min(block, total - start)
        out = run(pad(part, block), *shared)
        pieces.append(jax.tree.map(lambda a, n=n: np.asarray(a)[:n], out))
        if progress is not None:
            progress(start + n, total)
    return jax.tree.map(lambda *xs: np.concatenate(xs), *pieces)


# ---------------------------------------------------------------- past one machine
#
# jax.distributed (JAX's multi-controller runtime) joins N processes, one per host or GPU
# group. Each computes on its own local devices (devices() above) the share of the blocks that
# partition() gives it; results reach process 0 through the runtime's key-value store
# (publish / fetch), so no shared file system is needed.

#: Environment variables read when the options are not given (then SLURM / Open MPI).
ENV = {
    "coordinator": "JAXCART_COORDINATOR",
    "num_processes": "JAXCART_NUM_PROCESSES",
    "process_id": "JAXCART_PROCESS_ID",
}


def cluster_settings(coordinator=None, num_processes=None, process_id=None, environ=None):
    """``(coordinator, num_processes, process_id)`` from the options, else the JAXCART_*
    variables; ``"auto"`` when none is set but a scheduler (SLURM, Open MPI) started several
    processes (jax.distributed detects the rest); ``None`` for a single process.

    A clear :class:`jaxcart.errors.UserError` names a bad or missing setting."""
    env = os.environ if environ is None else environ
    given = {"coordinator": coordinator, "num_processes": num_processes, "process_id": process_id}
    where = {}
    for name, value in given.items():
        where[name] = f"--{name.replace('_', '-')}"
        if value is None and env.get(ENV[name], "").strip():
            given[name], where[name] = env[ENV[name]].strip(), ENV[name]
    if all(v is None for v in given.values()):
        if _scheduler_processes(env) > 1:
            return "auto"
        return None
    missing = [f"--{n.replace('_', '-')} (or {ENV[n]})" for n, v in given.items() if v is None]
    if missing:
        raise UserError(f"a distributed run needs {', '.join(missing)} as well")
    host, _, port = str(given["coordinator"]).rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UserError(
            f"{where['coordinator']} {given['coordinator']!r}: give HOST:PORT of process 0, "
            "e.g. node0:12345"
        )
    try:
        n = int(given["num_processes"])
    except ValueError:
        n = 0
    if n < 1:
        raise UserError(
            f"{where['num_processes']} {given['num_processes']!r}: give a whole number >= 1"
        )
    try:
        i = int(given["process_id"])
    except ValueError:
        i = -1
    if not 0 <= i < n:
        raise UserError(
            f"{where['process_id']} {given['process_id']!r}: give a whole number from 0 to {n - 1}"
        )
    return None if n == 1 else (str(given["coordinator"]), n, i)


def _scheduler_processes(env) -> int:
    # Set by mpirun and by srun for each task of a job step (not by salloc/sbatch alone,
    # where one process runs the command and must not wait for partners).
    for name in ("OMPI_COMM_WORLD_SIZE", "SLURM_STEP_NUM_TASKS"):
        if env.get(name, "").isdigit():
            return int(env[name])
    return 1


def init_distributed(settings, *, timeout_s: int = 300) -> bool:
    """Join the cluster of :func:`cluster_settings` (before any computation); True when this
    process is one of several. Safe to call twice."""
    if settings is None:
        return False
    if _dist.global_state.client is not None:
        return True
    try:
        if settings == "auto":
            jax.distributed.initialize(initialization_timeout=timeout_s)
        else:
            coordinator, n, i = settings
            jax.distributed.initialize(coordinator, n, i, initialization_timeout=timeout_s)
    except Exception as exc:  # the runtime raises XlaRuntimeError, RuntimeError, ValueError
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        what = "the cluster" if settings == "auto" else f"{settings[0]} as process {settings[2]}"
        raise UserError(
            f"cannot join {what}: {first[:200]}; start process 0 first and check the address"
        ) from None
    return True


def process_index() -> int:
    """This process's index in a distributed run (0 alone)."""
    return jax.process_index()


def process_count() -> int:
    """Number of processes in a distributed run (1 alone)."""
    return jax.process_count()


def partition(n_items: int, index: int | None = None, count: int | None = None) -> range:
    """Items (e.g. grid blocks) this process computes: every ``count``-th from ``index``
    (round robin balances the load and gives process 0 the first item)."""
    index = process_index() if index is None else index
    count = process_count() if count is None else count
    return range(index, n_items, count)


def _client():
    if _dist.global_state.client is None:
        raise RuntimeError("no distributed runtime: call init_distributed first")
    return _dist.global_state.client


def publish(key: str, data: bytes) -> None:
    """Store ``data`` under ``key`` in the distributed runtime (process 0 reads it)."""
    _client().key_value_set_bytes(key, data)


def fetch(key: str, timeout_s: float = 3600.0, *, delete: bool = True) -> bytes:
    """The bytes another process published under ``key``, waiting up to ``timeout_s``."""
    client = _client()
    data = client.blocking_key_value_get_bytes(key, int(timeout_s * 1000))
    if delete:
        client.key_value_delete(key)
    return data


def barrier(name: str, timeout_s: float = 3600.0) -> None:
    """Wait until every process reaches the barrier ``name``; no-op for a single process."""
    if process_count() > 1:
        _client().wait_at_barrier(name, int(timeout_s * 1000))


__all__ = [
    "AXIS",
    "ENV",
    "barrier",
    "cluster_settings",
    "fetch",
    "init_distributed",
    "partition",
    "process_count",
    "process_index",
    "publish",
    "positive",
    "put",
    "batch_sharding",
    "batch_size",
    "devices",
    "empty_result",
    "map_blocks",
    "mesh",
    "pad",
    "padded_size",
    "replicated",
    "sharded_map",
    "use_cpu_devices",
]
