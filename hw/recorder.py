"""The recording of a hardware run, written as it goes in the experiment-file format.

Both files are created at the start, exclusively (an existing recording is never replaced): the
TOML describes the run ([controller], [device], [run] status = "running") and the CSV gets one
row per sample (t, y, v, r, e and the loop's t_wall, compute), flushed every ``flush_every``
samples, so that a crash loses at most that fraction of a second and leaves a file that reads.
``close`` rewrites the TOML (beside it, then renamed) with the timing statistics and how the run
ended ([timing], [run] status, fault).
"""

from __future__ import annotations

import os
from pathlib import Path

from hw.control_law import PID
from hw.expfile import ExpFileError, experiment_paths, toml_lines

#: Columns of a hardware recording, in order.
RUN_COLUMNS = ("t", "y", "v", "r", "e", "t_wall", "compute")


class RunRecorder:
    """Append-only recording of one closed-loop run; ``path`` is the TOML file."""

    def __init__(
        self,
        path,
        controller: PID,
        *,
        description: str | None = None,
        tables: dict | None = None,
        flush_every: int = 100,
    ):
        self.path, self.csv_path = experiment_paths(Path(path))
        self.controller = controller
        self.description = description
        self.tables = {name: dict(table) for name, table in (tables or {}).items()}
        self.flush_every = max(1, int(flush_every))
        self.rows = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for p in (self.path, self.csv_path):
            if p.exists():
                raise ExpFileError(
                    f"{p} exists; a recording is never overwritten: choose another --out"
                )
        try:
            self._csv = self.csv_path.open("x", newline="")
        except FileExistsError:
            raise ExpFileError(f"{self.csv_path} exists; choose another --out") from None
        try:
            with self.path.open("x") as f:
                f.write(self._toml({"run": {"status": "running"}}))
        except FileExistsError:
            self._csv.close()
            os.unlink(self.csv_path)
            raise ExpFileError(f"{self.path} exists; choose another --out") from None
        self._csv.write(",".join(RUN_COLUMNS) + "\n")
        self._csv.flush()
        self._write = self._csv.write

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

    def row(self, t, y, v, r, t_wall, compute) -> None:
        """One sample (floats: [s], [m], [V], [m], [s], [s]); repr is the exact round trip."""
        self._write(f"{t!r},{y!r},{v!r},{r!r},{r - y!r},{t_wall!r},{compute!r}\n")
        self.rows += 1
        if self.rows % self.flush_every == 0:
            self._csv.flush()

    def close(self, tables: dict) -> Path:
        """Flush the data and rewrite the TOML with ``tables`` (merged into those given)."""
        if not self._csv.closed:
            self._csv.flush()
            self._csv.close()
        text = self._toml(tables)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        tmp.write_text(text)
        os.replace(tmp, self.path)  # a crash here leaves the "running" TOML, never half of one
        return self.path
