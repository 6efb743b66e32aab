"""The persistent compilation cache: XLA programs compiled once are kept on disk and reused by
later runs, so a second ``jaxcart tune`` or ``fit`` skips most of its compile time.

On by default for the command line, in the user's cache folder ($XDG_CACHE_HOME/jaxcart/xla,
else ~/.cache/jaxcart/xla): safe to delete at any time (it is rebuilt as needed). Off with
``jaxcart --no-cache ...`` or the environment variable JAXCART_NO_CACHE=1. Importing this module
imports no jax.

The folder is capped at :data:`MAX_BYTES` (1 GiB; JAXCART_CACHE_MAX_BYTES sets another cap):
each time jaxcart's own folder is turned on, :func:`prune` removes the least recently used
programs beyond it. Only JAX's entries directly in jaxcart's own folder are ever removed (a
folder given to :func:`enable_persistent_cache` is never pruned). JAX's own cap,
``jax_compilation_cache_max_size``, is not used: it needs the ``filelock`` package, takes a
file lock on every cache read and write, and fails every write in a folder of entries written
without it, as every existing jaxcart cache is, since it reads an access-time file each entry
lacks.
"""

from __future__ import annotations

import contextlib
import os
import stat
import sys
from pathlib import Path

#: Programs that compile faster than this [s] are not worth a disk write.
MIN_COMPILE_SECONDS = 0.2
#: Most bytes the compiled programs may take in the folder (1 GiB; a program is 0.1-0.4 MB on
#: a CPU, so a few thousand programs, many full lab runs' worth).
MAX_BYTES = 1 << 30
#: The environment variable that sets another cap [bytes].
MAX_BYTES_VARIABLE = "JAXCART_CACHE_MAX_BYTES"
#: Name endings of JAX's cache entries (the program; the access time JAX's own LRU cap keeps).
ENTRY_SUFFIX = "-cache"
ATIME_SUFFIX = "-atime"


def cache_dir() -> Path:
    """Where compiled programs are kept."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxcart" / "xla"


#: The folder enable_persistent_cache chose (jaxcart's own; jaxcart.aot keeps its programs
#: beside it).
ENABLED: Path | None = None


def enable_persistent_cache(folder: Path | None = None) -> Path | None:
    """Turn the cache on (unless JAXCART_NO_CACHE is set); returns the folder, or None."""
    global ENABLED
    if os.environ.get("JAXCART_NO_CACHE", "").strip() not in ("", "0"):
        return None
    folder = Path(folder) if folder is not None else cache_dir()
    ENABLED = folder
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # an unwritable home: run without the cache rather than fail
    if folder.resolve() == cache_dir().resolve():  # only jaxcart's own folder is pruned
        prune(folder, max_bytes())
    if "jax" in sys.modules:
        # lazy: jax costs 0.3 s at start-up (python -X importtime): already loaded here, and this
        # module imports no jax, for main before jax starts
        import jax

        jax.config.update("jax_compilation_cache_dir", str(folder))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    else:  # read by jax when it starts
        os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(folder))
        os.environ.setdefault(
            "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(MIN_COMPILE_SECONDS)
        )
    return folder


def max_bytes() -> int:
    """The cap [bytes]: JAXCART_CACHE_MAX_BYTES when it is a whole number >= 0 (a warning and
    :data:`MAX_BYTES` otherwise), else :data:`MAX_BYTES`."""
    text = os.environ.get(MAX_BYTES_VARIABLE, "").strip()
    if not text:
        return MAX_BYTES
    if text.isdigit():
        return int(text)
    print(
        f"jaxcart: {MAX_BYTES_VARIABLE}={text!r} is not a whole number of bytes; the cache "
        f"keeps its default cap of {MAX_BYTES} bytes",
        file=sys.stderr,
    )
    return MAX_BYTES


def prune(folder: Path, max_bytes: int | None = None) -> int:
    """Remove the least recently used compiled programs of ``folder`` (jaxcart's cache folder)
    until those left take at most ``max_bytes`` (default :data:`MAX_BYTES`); returns how many
    were removed.

    Only JAX's entries directly in ``folder`` count and go: regular files named ``*-cache``
    (with their ``*-atime`` files); nothing in a subfolder, no link, no other file. Recency is
    the later of a file's access and modification times: JAX reads an entry whole, which moves
    its access time where the file system keeps one (relatime, Linux's default, at least
    daily), else the entry ages from when it was written. A process that was about to read a
    removed entry compiles the program again (JAX warns that the read failed)."""
    limit = MAX_BYTES if max_bytes is None else int(max_bytes)
    if limit < 0:
        raise ValueError(f"max_bytes = {max_bytes!r}: give a number of bytes >= 0")
    entries, total = [], 0
    try:
        with os.scandir(folder) as it:
            for entry in it:
                if not entry.name.endswith(ENTRY_SUFFIX):
                    continue
                with contextlib.suppress(OSError):
                    st = entry.stat(follow_symlinks=False)
                    if stat.S_ISREG(st.st_mode):
                        entries.append((max(st.st_atime, st.st_mtime), st.st_size, entry.path))
                        total += st.st_size
    except OSError:  # no folder, or not readable: nothing to prune
        return 0
    if total <= limit:
        return 0
    entries.sort()  # oldest first
    removed = 0
    for _, size, path in entries:
        if total <= limit:
            break
        try:
            os.unlink(path)
        except FileNotFoundError:  # another process pruned it first
            total -= size
            continue
        except OSError:
            continue
        total -= size
        removed += 1
        with contextlib.suppress(OSError):
            os.unlink(path[: -len(ENTRY_SUFFIX)] + ATIME_SUFFIX)
    return removed
