"""Traced programs kept on disk, so that a new process skips Python tracing as well as XLA
compilation.

The persistent compilation cache (:mod:`jaxcart.cache`) keeps compiled XLA programs, but a new
process still traces and lowers every jitted function before it can look one up: about 1 s
for the tuner's iteration (a forward-mode pass through a 3001-step scan) against 0.02 s for
the iteration itself. :func:`jit` keeps the lowered program as well, serialized with
``jax.export``, in ``programs/`` beside the compilation cache: a later process deserializes
it (milliseconds), and its compilation is then served by the compilation cache.

A program is filed under a hash of everything that shapes it: the caller's name and static
settings, the argument tree and every leaf's shape, dtype, weak type and sharding, the JAX
version, the platform and device count, the float width, and the source of the jaxcart and
tuning packages (an edited module never runs a stale program). On and off with the
compilation cache (``JAXCART_NO_CACHE=1`` or ``jaxcart --no-cache``): the folder is safe to
delete. Anything that goes wrong on the way (no ``flatbuffers``, an unreadable or stale file,
a function ``jax.export`` cannot take) falls back to plain ``jax.jit``, silently.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pickle
import tempfile
from collections.abc import Callable, Hashable
from importlib import metadata
from pathlib import Path

import jax
import numpy as np

from jaxcart import cache

#: Bump when the file layout changes.
FORMAT = 1
#: Programs kept in the folder: the oldest beyond this are removed when one is written (each
#: edit of the source files a new set; a set is a few programs of 10-100 kB).
MAX_PROGRAMS = 256

_SOURCE_HASH: str | None = None


def programs_dir() -> Path | None:
    """Where exported programs are kept (jaxcart's own folder, beside the compilation cache
    that :func:`jaxcart.cache.enable_persistent_cache` chose), or None when the caches are
    off. Never a folder of the user's own JAX cache setting: programs are unpickled, so they
    live only in a folder of jaxcart's that this user owns."""
    if os.environ.get("JAXCART_NO_CACHE", "").strip() not in ("", "0"):
        return None
    if not jax.config.jax_compilation_cache_dir:  # only worth it where compilations are kept
        return None
    base = cache.ENABLED if cache.ENABLED is not None else cache.cache_dir()
    return base.parent / "programs"


def _trusted(path: Path) -> bool:
    """The file and its folder belong to this user and nobody else may write them."""
    if not hasattr(os, "getuid"):
        return True
    for p in (path.parent, path):
        st = p.stat()
        if st.st_uid != os.getuid() or st.st_mode & 0o022:
            return False
    return True


def source_hash() -> str:
    """Digest of what ends up in the programs: the source of jaxcart, tuning and hw (the
    control law), and the versions of jaxlib and optax (traced into the tuner)."""
    global _SOURCE_HASH
    if _SOURCE_HASH is None:
        h = hashlib.sha256()
        for dist in ("jaxlib", "optax"):
            try:
                h.update(f"{dist}={metadata.version(dist)}".encode())
            except metadata.PackageNotFoundError:
                pass
        root = Path(__file__).resolve().parent.parent
        for package in ("jaxcart", "tuning", "hw"):
            for path in sorted((root / package).rglob("*.py")):
                h.update(str(path.relative_to(root)).encode())
                try:
                    h.update(path.read_bytes())
                except OSError:
                    h.update(b"unreadable")
        _SOURCE_HASH = h.hexdigest()
    return _SOURCE_HASH


def _leaf_signature(x) -> tuple:
    """What jit specializes on, cheaply (this runs on every call)."""
    if isinstance(x, jax.Array):
        return (x.shape, x.dtype, x.weak_type, x.sharding if x.committed else None)
    if isinstance(x, np.ndarray | np.generic):
        return (x.shape, x.dtype)
    return (type(x),)  # a Python scalar: weakly typed


def _stable(part) -> str:
    """A signature leaf as text that is the same in every process."""
    if len(part) == 4 and part[3] is not None:
        shape, dtype, weak, sharding = part
        spec = getattr(sharding, "spec", None)
        return repr((shape, str(dtype), weak, str(spec), len(sharding.device_set)))
    if len(part) == 1:
        return part[0].__name__
    return repr(tuple(str(p) if not isinstance(p, tuple | bool) else p for p in part))


def _as_array(x):
    # device_put, not jnp.asarray: a Python number stays weakly typed and nothing compiles.
    return x if isinstance(x, jax.Array | np.ndarray | np.generic) else jax.device_put(x)


def _spec(x):
    x = _as_array(x)
    # Only where the caller placed the array: an uncommitted one goes where jit puts it.
    sharding = x.sharding if isinstance(x, jax.Array) and x.committed else None
    weak = bool(getattr(x, "weak_type", False))
    return jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=weak, sharding=sharding)


class Program:
    """``jax.jit(fn)`` whose lowered programs are kept on disk (see the module docstring).

    Positional array arguments (any pytrees) only; returns what ``fn`` returns."""

    def __init__(self, fn: Callable, name: str, static: Hashable = ()):
        self.fn = fn
        self.name = name
        self.static = static
        self._jit = jax.jit(fn)
        self._calls: dict = {}
        #: Where each signature's program came from: "disk", "export" or "jit" (plain jit).
        self.sources: list[str] = []

    def __call__(self, *args):
        leaves, tree = jax.tree.flatten(args)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return self._jit(*args)  # inside another transformation: nest like jax.jit
        signature = (
            tree,
            tuple(_leaf_signature(x) for x in leaves),
            bool(jax.config.jax_enable_x64),
        )
        entry = self._calls.get(signature)
        if entry is None:
            entry = self._prepare(leaves, tree, signature)
            if entry is not False:
                try:  # the first call compiles: a program this JAX cannot take falls back
                    out = entry[0](*map(_as_array, leaves))
                except Exception:
                    entry = False
                else:
                    self._calls[signature] = entry
                    self.sources.append(entry[2])
                    return jax.tree.unflatten(entry[1], out)
            self._calls[signature] = False
            self.sources.append("jit")
        if entry is False:
            return self._jit(*args)
        call, out_tree, _ = entry
        return jax.tree.unflatten(out_tree, call(*map(_as_array, leaves)))

    def cache_size(self) -> int:
        """Argument signatures prepared in this process: each one a program."""
        return len(self._calls)

    def _key(self, signature) -> str:
        tree, leaves, x64 = signature
        h = hashlib.sha256(f"jaxcart-aot-{FORMAT}-{jax.__version__}".encode())
        leaves = "|".join(_stable(p) for p in leaves)
        for part in (self.name, repr(self.static), str(tree), leaves, str(x64)):
            h.update(part.encode())
            h.update(b"\0")
        h.update(jax.default_backend().encode())
        h.update(str(jax.device_count()).encode())
        h.update(source_hash().encode())
        return h.hexdigest()[:32]

    def _prepare(self, leaves, tree, signature):
        """(call on the flat leaves, output tree, source) from the disk, else exported and
        saved; False where only plain jit works."""
        folder = programs_dir()
        if folder is None:
            return False
        try:
            # lazy: jax.export may be absent (an older JAX: plain jit then, below)
            from jax import export
        except ImportError:  # an older JAX
            return False
        path = folder / f"{self.name}-{self._key(signature)}.bin"
        try:
            if not _trusted(path):
                raise PermissionError(path)
            blob, out_tree = pickle.loads(path.read_bytes())
            exported = export.deserialize(bytearray(blob))
            return jax.jit(exported.call), out_tree, "disk"
        except FileNotFoundError:
            pass
        except Exception:  # a damaged, stale or foreign file: replaced below
            with contextlib.suppress(OSError):
                path.unlink(missing_ok=True)

        holder = {}

        def flat(*xs):
            out = self.fn(*jax.tree.unflatten(tree, xs))
            flat_out, holder["tree"] = jax.tree.flatten(out)
            return flat_out

        try:
            exported = export.export(jax.jit(flat))(*map(_spec, leaves))
            blob = exported.serialize()
        except Exception:  # something jax.export cannot take (or no flatbuffers)
            return False
        tmp = None
        try:
            folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            data = pickle.dumps((bytes(blob), holder["tree"]))
            with tempfile.NamedTemporaryFile(dir=folder, delete=False, suffix=".tmp") as f:
                tmp = f.name
                f.write(data)
            os.replace(tmp, path)
            prune(folder)
        except Exception:  # not kept: this process still runs the exported program
            if tmp is not None:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
        # Run the exported program here too, so the compilation cache holds the very program
        # the next process will compile.
        return jax.jit(exported.call), holder["tree"], "export"


def prune(folder: Path, keep: int | None = None) -> int:
    """Remove all but the ``keep`` (default :data:`MAX_PROGRAMS`) most recently written
    programs of ``folder``; returns how many were removed. A process that was about to read
    a removed one exports it again."""
    keep = MAX_PROGRAMS if keep is None else keep
    files = []
    for p in folder.glob("*.bin"):
        with contextlib.suppress(OSError):
            files.append((p.stat().st_mtime, p))
    files.sort(reverse=True)
    removed = 0
    for _, p in files[keep:]:
        with contextlib.suppress(OSError):
            p.unlink()
            removed += 1
    return removed


def jit(fn: Callable, name: str, static: Hashable = ()) -> Program:
    """:class:`Program` of ``fn``: ``name`` (a file-name-safe word) and ``static`` (a value
    whose ``repr`` names every setting ``fn`` closes over) file its programs."""
    return Program(fn, name, static)


__all__ = ["Program", "jit", "programs_dir", "source_hash"]
