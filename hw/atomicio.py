"""Atomic writing of output files (numpy-free: the standard library only, so hw/ uses it too).

Every output is written to a temporary name in its target's folder, flushed to the disk, then
renamed onto the target: a full disk, a read-only folder, a crash or Ctrl-C in the middle
leaves either the finished file or nothing, never half a file that then blocks the rerun
("exists; choose another name"). Several files that belong together (an experiment's TOML and
CSV) are renamed together: if one cannot be written, none is left.

    with atomic_paths("run.toml", "run.csv") as (toml_tmp, csv_tmp):
        csv_tmp.write_text(...)              # any writer that takes a path
        toml_tmp.write_text(...)
    # both in place now, or neither

A failure is an :class:`OutputError` whose one line names the file, the cause (disk full,
read-only, permission denied) and the fix.
"""

from __future__ import annotations

import errno
import os
from contextlib import contextmanager
from pathlib import Path


class OutputError(ValueError):
    """An output that cannot be written; the message is one line: file, cause, fix."""


#: What each errno means for someone writing an output, and what to do about it.
_CAUSES = {
    errno.ENOSPC: ("the disk is full", "free some space or choose another folder"),
    errno.EDQUOT: ("the disk quota is used up", "free some space or choose another folder"),
    errno.EROFS: ("the file system is read-only", "choose a folder you can write to"),
    errno.EACCES: ("permission denied", "choose a folder you can write to"),
    errno.EPERM: ("permission denied", "choose a folder you can write to"),
    errno.EISDIR: ("it is a folder", "give a file name inside it"),
    errno.ENOTDIR: ("a part of the path is a file", "choose another folder"),
    errno.ENAMETOOLONG: ("the name is too long", "choose a shorter name"),
}


def describe(path, exc: OSError) -> str:
    """One line for an OSError met while writing ``path``: the cause and the fix."""
    cause, fix = _CAUSES.get(exc.errno, (exc.strerror or str(exc), "choose another folder"))
    return f"cannot write {path}: {cause}; {fix} (nothing was written)"


def exists_message(path) -> str:
    return f"{path} exists; choose another name or pass --force to overwrite it"


def temporary_name(path) -> Path:
    """A hidden name beside ``path`` that keeps its suffix (matplotlib picks the format from
    it): ``folder/.name.<pid>.tmp.png`` for ``folder/name.png``."""
    path = Path(path)
    return path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")


#: How a temporary file is opened; tests replace it to simulate a full disk.
_open = open


def open_output(tmp, mode: str = "w", **kwargs):
    """Open a temporary path from :func:`atomic_paths` for writing (the one place outputs are
    opened, so a test can make every write meet a full disk)."""
    if "b" not in mode:
        kwargs.setdefault("encoding", "utf-8")
    return _open(tmp, mode, **kwargs)


@contextmanager
def atomic_paths(*paths, force: bool = False):
    """Yield a temporary path for each target in ``paths`` (same folder, same suffix); when
    the block ends without an exception, each temporary file is flushed to disk and renamed
    onto its target, in the order given. On any exception, or when a rename fails, the
    temporary files and the targets renamed so far are removed and the exception is raised,
    an OSError as :class:`OutputError`. Without ``force`` an existing target is refused,
    before the block runs and again at the rename (a file that appeared meanwhile)."""
    paths = [Path(p) for p in paths]
    if not force:
        for path in paths:
            if path.exists():
                raise OutputError(exists_message(path))
    made = missing_folders(paths)
    current = paths[0] if paths else None
    temps = [temporary_name(p) for p in paths]
    done: list[Path] = []
    try:
        for path in paths:
            current = path
            path.parent.mkdir(parents=True, exist_ok=True)
        yield temps
        for path, tmp in zip(paths, temps, strict=True):
            current = path
            _sync(tmp)
            _rename(tmp, path, force)
            done.append(path)
    except OSError as exc:
        _remove(temps + done)
        remove_empty(made)
        raise OutputError(describe(current, exc)) from None
    except BaseException:
        _remove(temps + done)
        remove_empty(made)
        raise


@contextmanager
def atomic_open(path, mode: str = "w", *, force: bool = False, **kwargs):
    """``open(path, mode)`` through a temporary name (see :func:`atomic_paths`); mode "w"
    or "wb". The file appears whole when the block ends, or not at all."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open: mode {mode!r}; use 'w' or 'wb'")
    with atomic_paths(path, force=force) as (tmp,):
        with open_output(tmp, mode, **kwargs) as f:
            yield f


def write_text(path, text: str, *, force: bool = False, newline: str | None = None) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_open(path, "w", force=force, newline=newline) as f:
        f.write(text)
    return Path(path)


def write_bytes(path, data: bytes, *, force: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_open(path, "wb", force=force) as f:
        f.write(data)
    return Path(path)


def save_figure(fig, path, *, force: bool = True, **kwargs) -> Path:
    """``fig.savefig(path, **kwargs)`` atomically (a matplotlib figure; the format is taken
    from the suffix of ``path`` unless given)."""
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".").lower() or None)
    with atomic_open(path, "wb", force=force) as f:
        fig.savefig(f, **kwargs)
    return path


@contextmanager
def all_or_none(*paths):
    """Outputs of one command, kept together or not at all: when the block raises, each of
    ``paths`` (None entries are skipped) that did not exist as it began is removed, so a full
    disk at the last of three files leaves none of them to block the rerun. Each file is
    still best written atomically (a failed write leaves no half file of its own). The folders
    made on the way to them go too, where they are left empty."""
    paths = [Path(p) for p in paths if p is not None]
    new = [p for p in paths if not p.exists()]
    made = missing_folders(paths)
    try:
        yield
    except BaseException:
        _remove([p for p in new if p.is_file()])
        remove_empty(made)
        raise


def missing_folders(paths) -> list[Path]:
    """The folders on the way to ``paths`` (files) that do not exist yet, deepest first: what
    writing them creates, and a command that fails removes again (an empty output folder left
    behind reads as a result, and may block the rerun)."""
    out: list[Path] = []
    for path in paths:
        folder = Path(path).parent
        while not folder.exists() and folder != folder.parent and folder not in out:
            out.append(folder)
            folder = folder.parent
    return sorted(out, key=lambda f: len(f.parts), reverse=True)


def remove_empty(folders) -> None:
    """Remove each of ``folders`` (deepest first) that exists and is empty; one that holds
    anything stays, with what it holds."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty, gone already, or not ours to remove
            pass


def _sync(tmp: Path) -> None:
    """Flush ``tmp`` to the disk: a full disk can show only now, and a rename of data not yet
    written could leave an empty file after a power loss."""
    if not tmp.exists():  # the block wrote nothing there (an empty output is still an output)
        with _open(tmp, "wb"):
            pass
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _rename(tmp: Path, path: Path, force: bool) -> None:
    if force:
        os.replace(tmp, path)
        return
    try:  # a hard link fails if the target appeared meanwhile: never over a user's file
        os.link(tmp, path)
    except FileExistsError:
        raise OutputError(exists_message(path)) from None
    except OSError:  # a file system without hard links
        if path.exists():
            raise OutputError(exists_message(path)) from None
        os.replace(tmp, path)
        return
    tmp.unlink()


def _remove(paths) -> None:
    for path in paths:
        try:
            path.unlink()
        except OSError:
            pass
