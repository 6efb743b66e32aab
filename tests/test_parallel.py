"""The device layer (jaxcart.parallel) against plain jax.vmap on one device: any batch size,
pytree batches and results, chunking, shared arguments; and the distributed settings."""

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcart import parallel
from jaxcart.errors import UserError


def _fn(item, scale):
    """A pytree in (dict of a vector and a scalar), a pytree out (tuple), a shared argument."""
    x, a = item["x"], item["a"]
    return (scale * jnp.sin(x) * a, {"norm": jnp.sum(x**2) + a})


_RUN = parallel.sharded_map(_fn)
_RUN_CHUNKED = parallel.sharded_map(_fn, chunk=2)


def _batch(n, seed=0):
    rng = np.random.default_rng(seed)
    return {"x": rng.normal(size=(n, 3)), "a": rng.normal(size=n)}


def _reference(batch, scale):
    return jax.vmap(_fn, in_axes=(0, None))(batch, scale)


@pytest.mark.parametrize(
    "run, n", [(_RUN, 1), (_RUN, 7), (_RUN_CHUNKED, 5)], ids=["one-1", "one-7", "chunk2-5"]
)
def test_sharded_map_equals_vmap(run, n):
    assert len(parallel.devices()) == 2  # conftest: two CPU devices
    batch = _batch(n, seed=n)
    got, want = run(batch, 1.5), _reference(batch, 1.5)
    assert jax.tree.structure(got) == jax.tree.structure(want)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        assert g.shape == w.shape and g.shape[0] == n
        # Same operations on the same numbers; only XLA's fusion may differ: rounding.
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-13, atol=1e-15)


def test_whole_chunks_hand_fn_each_chunk():
    """``whole_chunks=True``: fn maps a whole chunk itself (its leading axis the chunk's)."""
    seen = []

    def chunk_fn(block, scale):
        seen.append(block["x"].shape)
        return jax.vmap(_fn, in_axes=(0, None))(block, scale)

    run = parallel.sharded_map(chunk_fn, chunk=2, cache=False, whole_chunks=True)
    batch = _batch(7, seed=5)
    got, want = run(batch, 0.5), _reference(batch, 0.5)
    assert seen == [(2, 3)]  # traced once, on one chunk of 2 runs
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        assert g.shape == w.shape
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-13, atol=1e-15)


def test_sharded_output_is_split_over_the_mesh_and_cached():
    out = _RUN_CHUNKED(_batch(8), 1.0)
    assert len(out[0].sharding.device_set) == 2
    assert parallel.sharded_map(_fn, chunk=2) is _RUN_CHUNKED
    assert parallel.sharded_map(_fn, chunk=2, cache=False) is not _RUN_CHUNKED


def test_map_blocks_equals_one_call_and_reports_progress():
    batch = _batch(11, seed=3)
    seen = []
    got = parallel.map_blocks(
        _fn, batch, 0.5, chunk=2, block=4, progress=lambda d, t: seen.append((d, t))
    )
    want = _reference(batch, 0.5)
    assert seen == [(4, 11), (8, 11), (11, 11)]
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        assert isinstance(g, np.ndarray) and g.shape == w.shape
        np.testing.assert_allclose(g, np.asarray(w), rtol=1e-13, atol=1e-15)


def test_empty_batch_gives_empty_results_of_the_right_shapes_and_dtypes():
    """0 items: nothing compiled or run, every leaf of the result with the shape and dtype a
    batch of items gives (found by tracing fn on one item's shapes), leading axis 0."""

    def fn(item, scale):
        x, a = item["x"], item["a"]
        return (scale * jnp.sin(x) * a, {"norm": jnp.sum(x**2) + a, "n": jnp.int32(3)})

    full = jax.vmap(fn, in_axes=(0, None))(_batch(3), 0.5)
    empty = _batch(0)
    for got, host in (
        (parallel.sharded_map(fn, chunk=2, cache=False)(empty, 0.5), False),
        (parallel.map_blocks(fn, empty, 0.5, chunk=2, block=4), True),
    ):
        assert jax.tree.structure(got) == jax.tree.structure(full)
        for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(full), strict=True):
            assert isinstance(g, np.ndarray) == host
            assert g.shape == (0,) + w.shape[1:] and g.dtype == w.dtype
    # A whole-chunk fn: its result's leading axis is the chunk's.
    whole = parallel.sharded_map(lambda c, k: k * c["x"], cache=False, whole_chunks=True)
    assert whole(empty, 2.0).shape == (0, 3)
    # Progress is reported per block: an empty batch has none.
    seen = []
    parallel.map_blocks(_fn, empty, 1.0, progress=lambda d, t: seen.append((d, t)))
    assert seen == []


def test_empty_batch_that_fn_cannot_trace_and_bad_sizes_are_clear_errors():
    def needs_data(item, scale):
        if float(item["a"]) > 0:  # concrete values only: no shapes without data
            return item["x"]
        return -item["x"]

    with pytest.raises(ValueError, match="empty batch.*without data.*at least one item"):
        parallel.map_blocks(needs_data, _batch(0), 1.0)
    with pytest.raises(ValueError, match="chunk = 0"):
        parallel.sharded_map(_fn, chunk=0)
    with pytest.raises(ValueError, match="block = -1"):
        parallel.map_blocks(_fn, _batch(3), 1.0, block=-1)
    with pytest.raises(ValueError, match="empty batch"):
        parallel.pad({"x": np.zeros((0, 3))}, 4)
    with pytest.raises(ValueError, match=">= 1"):
        parallel.padded_size(0, 0, 2)


def test_padding_repeats_the_last_item_on_the_host():
    padded = parallel.pad({"x": np.arange(3.0)}, 5)
    assert isinstance(padded["x"], np.ndarray)
    np.testing.assert_array_equal(padded["x"], [0, 1, 2, 2, 2])
    assert parallel.padded_size(5, 2, 2) == 8
    with pytest.raises(ValueError, match="same leading axis"):
        parallel.batch_size({"a": np.zeros(3), "b": np.zeros(4)})


def test_partition_covers_every_block_once():
    shares = [list(parallel.partition(10, i, 3)) for i in range(3)]
    assert sorted(sum(shares, [])) == list(range(10))
    assert shares[0][0] == 0 and list(parallel.partition(4)) == [0, 1, 2, 3]  # one process


def test_cluster_settings_from_options_and_environment():
    assert parallel.cluster_settings(environ={}) is None
    assert parallel.cluster_settings("h:1234", "2", "1", environ={}) == ("h:1234", 2, 1)
    env = {"JAXCART_COORDINATOR": "n0:99", "JAXCART_NUM_PROCESSES": "4", "JAXCART_PROCESS_ID": "3"}
    assert parallel.cluster_settings(environ=env) == ("n0:99", 4, 3)
    assert parallel.cluster_settings(process_id="0", environ=env) == ("n0:99", 4, 0)
    assert parallel.cluster_settings("h:1", 1, 0, environ={}) is None  # one process alone
    assert parallel.cluster_settings(environ={"SLURM_STEP_NUM_TASKS": "8"}) == "auto"
    assert parallel.cluster_settings(environ={"OMPI_COMM_WORLD_SIZE": "2"}) == "auto"
    assert parallel.cluster_settings(environ={"SLURM_STEP_NUM_TASKS": "1"}) is None
    assert parallel.cluster_settings(environ={"SLURM_NTASKS": "8"}) is None  # salloc alone


@pytest.mark.parametrize(
    "args, env, match",
    [
        (("h", "2", "0"), {}, "--coordinator 'h': give HOST:PORT"),
        (("h:0", "2", "0"), {}, "HOST:PORT"),
        (("h:1", "two", "0"), {}, "--num-processes 'two'"),
        (("h:1", "2", "2"), {}, "--process-id '2': give a whole number from 0 to 1"),
        (("h:1", None, None), {}, "needs --num-processes"),
        (
            (None, None, None),
            {"JAXCART_PROCESS_ID": "x", "JAXCART_NUM_PROCESSES": "2", "JAXCART_COORDINATOR": "a:1"},
            "JAXCART_PROCESS_ID 'x'",
        ),
    ],
)
def test_bad_cluster_settings_say_which(args, env, match):
    with pytest.raises(UserError, match=match):
        parallel.cluster_settings(*args, environ=env)


@pytest.mark.parametrize(
    "value, dtype",
    [
        (np.arange(6.0).reshape(2, 3), None),
        (np.arange(4), float),
        ([1.5, 2.5], float),
        (2.0, None),
        (3, None),
        (True, None),
        (np.array([True, False]), None),
        (np.arange(3), np.int32),
        (0.25, np.float64),
    ],
)
def test_put_equals_jnp_asarray_in_value_dtype_and_weak_type(value, dtype):
    """put is jnp.asarray without the compile: same values, dtype (canonical for the float
    width in force) and weak type; a JAX array passes through."""
    got, want = parallel.put(value, dtype), jnp.asarray(value, dtype)
    assert got.dtype == want.dtype
    assert got.weak_type == want.weak_type
    assert got.shape == want.shape
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    assert parallel.put(want) is want


def _compiles(fn) -> list[str]:
    """The compilations JAX logs while ``fn`` runs."""
    seen = []

    class Catch(logging.Handler):
        def emit(self, record):
            seen.append(record.getMessage())

    logger, handler = logging.getLogger("jax"), Catch()
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            fn()
    finally:
        logger.removeHandler(handler)
    return [m for m in seen if m.startswith("Compiling")]


def test_put_compiles_nothing_and_places_where_asked():
    # The control: jnp.asarray of a shape not seen before compiles (what put avoids).
    assert _compiles(lambda: jnp.asarray(np.zeros((13, 3))))
    assert not _compiles(lambda: parallel.put(np.zeros((7, 5)), float))
    assert not _compiles(lambda: parallel.put(np.zeros(11, bool), None, parallel.replicated()))
    assert not _compiles(lambda: parallel.put(0.125))
    y = parallel.put(np.ones((2, 3)), float, parallel.replicated())
    assert y.sharding == parallel.replicated()
    assert parallel.put(np.ones(3)).committed is False
