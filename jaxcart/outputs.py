"""Where commands write: never over a user's file unless asked (--force)."""

from __future__ import annotations

from pathlib import Path

#: Default folder of command outputs, in the current directory.
OUT_DIR = Path("jaxcart-out")


def free_names(folder: Path, stem: str, suffixes: tuple[str, ...]) -> tuple[Path, ...]:
    """``folder/stem{suffix}`` for each suffix, or ``stem-2``, ``stem-3``, ... : the first
    numbering at which none of the files exists (so outputs of one run share a name)."""
    folder = Path(folder)
    n = 1
    while True:
        name = stem if n == 1 else f"{stem}-{n}"
        paths = tuple(folder / f"{name}{suffix}" for suffix in suffixes)
        if not any(p.exists() for p in paths):
            return paths
        n += 1
