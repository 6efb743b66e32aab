"""Where commands write: never over a user's file unless asked (--force), and every output
checked before the computation starts, so that a bad path fails in a second, not after minutes.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from jaxcart.errors import UserError

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


def check_writable(
    path,
    *,
    suffixes: tuple[str, ...] | None = None,
    option: str | None = None,
    force: bool = True,
    folder: bool = False,
) -> Path:
    """Check that ``path`` can be written, before anything is computed; returns it as a Path.

    Raises :class:`UserError` (one line naming ``option``, e.g. "--out", and the fix) when the
    suffix is not one of ``suffixes`` (case-insensitive; None: any), when a parent on the way is
    a regular file, when the first existing parent folder is not writable, when the path is an
    existing folder (or, with ``folder=True``, an existing file), or when it exists and
    ``force`` is False. Missing parent folders are fine (commands create them); nothing is
    created here.
    """
    path = Path(path)
    label = f"{option} {path}" if option else str(path)
    if path.exists():
        if folder and not path.is_dir():
            raise UserError(f"{label} is a file, not a folder; give a folder name")
        if not folder and path.is_dir():
            raise UserError(f"{label} is a folder; give a file name inside it")
        if not force:
            raise UserError(f"{label} exists; choose another name or pass --force to overwrite it")
    if suffixes is not None and not folder:
        allowed = tuple(s.lower() for s in suffixes)
        if path.suffix.lower() not in allowed:
            raise UserError(
                f"{label}: unknown suffix {path.suffix or '(none)'!r}; give a name ending in "
                f"{' or '.join(suffixes)}"
            )
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise UserError(
            f"{label}: {parent} is a file, so nothing can be written under it; choose another "
            f"folder"
        )
    if not _can_write(path if path.exists() else parent):
        raise UserError(
            f"{label}: {path if path.exists() else parent} is not writable (permission denied "
            f"or a read-only file system); choose a folder you can write to"
        )
    return path


def _can_write(target: Path) -> bool:
    """Whether ``target`` (an existing file or folder) takes writes: a real probe, since
    os.access says yes to root on a read-only file system or /proc."""
    try:
        if target.is_dir():
            with tempfile.TemporaryFile(dir=target, prefix=".jaxcart-probe-"):
                pass
        else:
            with target.open("ab"):
                pass
    except OSError:
        return False
    return True
