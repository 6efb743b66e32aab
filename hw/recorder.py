"""The recording of a hardware run, written as it goes in the experiment-file format.

    start:  RUN.csv (header) and RUN.toml ([run] status = "running", space kept for the end)
            created exclusively: an existing recording is never replaced
    run:    rows kept in memory and written to the CSV every ``flush_every`` samples, whole lines
            only; a thread beside the loop fsyncs the CSV every ``sync_every`` seconds
    close:  the last rows, fsync, then the TOML rewritten to a temporary name, flushed and
            renamed over RUN.toml ([timing], [run] status, fault, samples)
    never started (fewer than 2 samples): both files removed, so a retry finds the name free

What each failure loses (``flush_every`` = 100, ``sync_every`` = 1 s, 1 kHz):
    the process killed (kill -9, a crash of Python): the rows since the last flush, <= 100
    a power loss: the rows since the last completed fsync, <= 1 s + the fsync's own time
    a full disk or an error writing the CSV: the file is cut back to its last whole line and
        the run stops (the loop's reason names the disk); the TOML is then rewritten in place,
        in the space kept at the start, if no temporary file can be written
    a folder that turns read-only: the open files are written in place the same way

File operations go through ``files`` (:class:`OsFiles`), so that tests can inject a full disk
or a read-only folder without one.
"""

from __future__ import annotations

import errno
import os
import threading
from pathlib import Path

from hw.control_law import PID
from hw.expfile import ExpFileError, experiment_paths, toml_lines

#: Columns of a hardware recording, in order.
RUN_COLUMNS = ("t", "y", "v", "r", "e", "t_wall", "compute")
#: Bytes kept free at the end of the TOML so that the end of the run can be written in place
#: on a full disk (the final TOML adds ~1.5 kB: [timing], the fault, the device as stopped).
RESERVE = 4096
#: Fewer samples than this and the run never started: the files are removed.
MIN_SAMPLES = 2


class RecorderError(OSError):
    """Writing the recording failed (a full disk, a read-only folder); the message says which
    file, why, and how many samples the CSV holds."""


class OsFiles:
    """The file operations of the recorder, on the operating system (tests replace them)."""

    def create(self, path: Path) -> int:
        """Open a new file for writing; FileExistsError if it exists."""
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
        return os.open(path, flags, 0o666)  # rw for whom the umask allows, as open() makes

    def open_existing(self, path: Path) -> int:
        return os.open(path, os.O_WRONLY | getattr(os, "O_BINARY", 0))

    def write(self, fd: int, data: bytes) -> int:
        return os.write(fd, data)

    def seek(self, fd: int, offset: int) -> None:
        os.lseek(fd, offset, os.SEEK_SET)

    def truncate(self, fd: int, size: int) -> None:
        os.ftruncate(fd, size)

    def fsync(self, fd: int) -> None:
        os.fsync(fd)

    def close(self, fd: int) -> None:
        os.close(fd)

    def replace(self, src: Path, dst: Path) -> None:
        os.replace(src, dst)

    def unlink(self, path: Path) -> None:
        os.unlink(path)

    def mkdir(self, path: Path) -> None:
        path.mkdir(parents=True, exist_ok=True)


def _why(exc: OSError) -> str:
    if exc.errno == errno.ENOSPC:
        return "the disk is full"
    if exc.errno == errno.EROFS:
        return "the file system is read-only"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return "the folder is read-only"
    if exc.errno == errno.ENOENT:
        return f"no such folder ({exc.filename})" if exc.filename else "no such folder"
    return exc.strerror or type(exc).__name__


class RunRecorder:
    """Append-only recording of one closed-loop run; ``path`` is the TOML file.

    rows: samples given to :meth:`row`; saved: samples whose lines are in the CSV file.
    """

    def __init__(
        self,
        path,
        controller: PID,
        *,
        description: str | None = None,
        tables: dict | None = None,
        flush_every: int = 100,
        sync_every: float = 1.0,
        files: OsFiles | None = None,
    ):
        self.path, self.csv_path = experiment_paths(Path(path))
        self.controller = controller
        self.description = description
        self.tables = {name: dict(table) for name, table in (tables or {}).items()}
        self.flush_every = max(1, int(flush_every))
        self.files = files or OsFiles()
        self.rows = self.saved = 0
        self.error: str | None = None
        self.closed = False
        self._pending: list[str] = []
        self._csv = self._toml_fd = None
        self._toml_size = 0
        self._created: list[Path] = []
        for p in (self.path, self.csv_path):
            if p.exists():
                raise ExpFileError(
                    f"{p} exists; a recording is never overwritten: choose another --out"
                )
        try:
            self._open()
        except BaseException as exc:
            self.close_files()
            self._remove_created()
            if isinstance(exc, OSError):
                raise ExpFileError(self._open_error(exc)) from None
            raise
        self._sync_stop = threading.Event()
        self._sync_errors: list[str] = []
        self._syncer = None
        if sync_every and sync_every > 0:
            self._syncer = threading.Thread(
                target=self._sync_loop, args=(float(sync_every),), daemon=True
            )
            self._syncer.start()

    # -- start

    def _open_error(self, exc: OSError) -> str:
        """One line on why the recording cannot be created, and what to do."""
        name = Path(exc.filename) if exc.filename else self.path
        if isinstance(exc, FileExistsError) and name in (self.path, self.csv_path):
            return f"{name} exists; a recording is never overwritten: choose another --out"
        if isinstance(exc, FileExistsError | NotADirectoryError):
            return f"cannot make the folder {self.path.parent}: a file is in the way ({name})"
        return (
            f"cannot write the recording {self.path}: {_why(exc)}; choose another --out (a "
            "folder you can write to, with free space)"
        )

    def _open(self) -> None:
        files = self.files
        files.mkdir(self.path.parent)
        self._csv = files.create(self.csv_path)
        self._created.append(self.csv_path)
        self._write_all(self._csv, (",".join(RUN_COLUMNS) + "\n").encode())
        self._committed = len(",".join(RUN_COLUMNS)) + 1
        text = self._toml({"run": {"status": "running"}}).encode()
        text += b"# " + b" " * (RESERVE - 3) + b"\n"  # kept for the end of the run (see close)
        self._toml_fd = files.create(self.path)
        self._created.append(self.path)
        self._write_all(self._toml_fd, text)
        self._toml_size = len(text)

    def _write_all(self, fd: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = self.files.write(fd, view)
            if not n:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            view = view[n:]

    def _toml(self, extra: dict) -> str:
        tables = dict(self.tables)
        for name, table in extra.items():
            tables[name] = {**tables.get(name, {}), **table}
        lines = toml_lines(
            kind="closed_loop",
            sample_time=self.controller.sample_time,
            csv_name=self.csv_path.name,
            columns=RUN_COLUMNS,
            controller=self.controller,
            description=self.description,
            tables=tables,
        )
        return "\n".join(lines) + "\n"

    # -- run

    def row(self, t, y, v, r, t_wall, compute) -> None:
        """One sample (floats: [s], [m], [V], [m], [s], [s]); repr is the exact round trip.
        Raises :class:`RecorderError` when the CSV cannot be written (the loop then stops)."""
        self._pending.append(f"{t!r},{y!r},{v!r},{r!r},{r - y!r},{t_wall!r},{compute!r}\n")
        self.rows += 1
        if len(self._pending) >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        """Write the rows kept in memory, whole lines only (a failed write is cut back)."""
        if self.error is not None:
            raise RecorderError(self.error)
        if not self._pending or self._csv is None:
            return
        data = "".join(self._pending).encode()
        view, written = memoryview(data), 0
        try:
            while written < len(data):
                n = self.files.write(self._csv, view[written:])
                if not n:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                written += n
        except BaseException as exc:
            # Keep the whole lines that did reach the file, cut the rest back.
            whole = data.rfind(b"\n", 0, written) + 1
            lines = data.count(b"\n", 0, whole)
            self._committed += whole
            self.saved += lines
            del self._pending[:lines]
            self._cut_back()
            if not isinstance(exc, OSError):
                self.error = f"recording: {type(exc).__name__} writing {self.csv_path.name}"
                raise
            self.error = (
                f"recording: {_why(exc)} ({exc.strerror}) writing {self.csv_path.name}; it "
                f"holds the first {self.saved} samples"
            )
            raise RecorderError(self.error) from None
        self._committed += len(data)
        self.saved += len(self._pending)
        self._pending.clear()

    def _cut_back(self) -> None:
        """Back to the last whole line after a write that may have written part of a chunk."""
        try:
            self.files.truncate(self._csv, self._committed)
            self.files.seek(self._csv, self._committed)
        except OSError:
            pass  # then the reader names the cut line; nothing more can be done here

    def _sync_loop(self, every: float) -> None:
        """fsync the CSV every ``every`` s, beside the loop (fsync releases the GIL)."""
        while not self._sync_stop.wait(every):
            try:
                self.files.fsync(self._csv)
            except Exception as exc:  # noqa: BLE001 - noted by close(); the loop goes on
                self._sync_errors.append(str(exc))
                return

    # -- end

    def discard(self) -> None:
        """The run never started: remove both files, so that the name is free for a retry."""
        self._stop_sync()
        self.close_files()
        self._remove_created()
        self.closed = True

    def _remove_created(self) -> None:
        for p in self._created:
            for _ in range(2):  # once more if a signal interrupts the first
                try:
                    self.files.unlink(p)
                    break
                except FileNotFoundError:
                    break
                except OSError:
                    break
        self._created = []

    def _stop_sync(self) -> None:
        syncer = getattr(self, "_syncer", None)
        if syncer is not None:
            self._sync_stop.set()
            syncer.join()
            self._syncer = None

    def close_files(self) -> None:
        """Close both files (the run's end could not be written: nothing more will be)."""
        for name in ("_csv", "_toml_fd"):
            fd = getattr(self, name)
            if fd is not None:
                setattr(self, name, None)
                try:
                    self.files.close(fd)
                except OSError:
                    pass

    def close(self, tables: dict) -> tuple[Path, list[str]]:
        """Write the last rows and the final TOML (``tables`` merged into those given).

        Returns (path, notes): what could not be done, one line each (empty when all was
        written). Never raises for a file error (the run's end is what matters here); any
        other exception is raised with the files left open, so that close can run again.
        """
        notes: list[str] = []
        self._stop_sync()
        if self._sync_errors:
            notes.append(f"recording: fsync failed: {self._sync_errors[0]}")
        if self.error is None:  # else the loop has the error as its reason already
            try:
                self.flush()
            except RecorderError as exc:
                notes.append(str(exc))
        try:
            if self._csv is not None:
                self.files.fsync(self._csv)
        except OSError as exc:
            notes.append(f"recording: fsync of {self.csv_path.name} failed ({exc.strerror})")
        text = self._toml(tables)
        try:
            self._replace_toml(text)
        except OSError as exc:
            note = self._toml_in_place(text, {"run": tables.get("run", {})}, exc)
            notes.append(note or f"recording: {self.path.name} finished in place ({_why(exc)})")
        self.close_files()
        self.closed = True
        return self.path, notes

    def _replace_toml(self, text: str) -> None:
        """The final TOML at a temporary name, flushed, renamed over the running one."""
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        fd = self.files.create(tmp)
        try:
            self._write_all(fd, text.encode())
            self.files.fsync(fd)
        except BaseException:
            self.files.close(fd)
            try:
                self.files.unlink(tmp)
            except OSError:
                pass
            raise
        self.files.close(fd)
        try:
            self.files.replace(tmp, self.path)
        except BaseException:
            try:
                self.files.unlink(tmp)
            except OSError:
                pass  # a read-only folder: the hidden temporary file stays, blocking nothing
            raise

    def _toml_in_place(self, text: str, short: dict, why: OSError) -> str | None:
        """The final TOML written over the running one, inside the space kept at the start
        (``short``: the tables that always fit, written when ``text`` does not)."""
        data = text.encode()
        if len(data) >= self._toml_size:
            data = self._toml(short).encode()
        if len(data) >= self._toml_size or self._toml_fd is None:
            return f"recording: the TOML could not be finished ({_why(why)})"
        data += b" " * (self._toml_size - len(data) - 1) + b"\n"
        try:
            self.files.seek(self._toml_fd, 0)
            self._write_all(self._toml_fd, data)
            self.files.fsync(self._toml_fd)
        except OSError as exc:
            return f"recording: the TOML still says running ({_why(exc)}: {exc.strerror})"
        return None
