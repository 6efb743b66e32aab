"""The persistent compilation cache: XLA programs compiled once are kept on disk and reused by
later runs, so a second ``jaxcart tune`` or ``fit`` skips most of its compile time.

On by default for the command line, in the user's cache folder ($XDG_CACHE_HOME/jaxcart/xla,
else ~/.cache/jaxcart/xla): safe to delete at any time (it is rebuilt as needed). Off with
``jaxcart --no-cache ...`` or the environment variable JAXCART_NO_CACHE=1. Importing this module
imports no jax.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: Programs that compile faster than this [s] are not worth a disk write.
MIN_COMPILE_SECONDS = 0.2


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
    if "jax" in sys.modules:
        import jax

        jax.config.update("jax_compilation_cache_dir", str(folder))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    else:  # read by jax when it starts
        os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(folder))
        os.environ.setdefault(
            "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(MIN_COMPILE_SECONDS)
        )
    return folder
