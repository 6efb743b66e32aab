"""Which recording is which part of the lab.

A data folder holds experiment files (the format of docs/experiment-files.md). Each is given
a *slot* of the lab:

    slot      part   what it is                                   how it is recognised
    tap       (i)    tap test, motor unplugged                    kind = "tap"
    p_step    (ii)   P control k = 50 V/m, step 0.4 m             closed loop, ki = kd = 0, kp != 10
    ramp      (iii)  open-loop voltage ramp 0.1 V/s               kind = "open_loop", ramp input
    p_error   (iii)  P control k = 10 V/m, step (e(inf) bound)    closed loop, ki = kd = 0, kp = 10
    pi        (iv)   PI control k = 10, k_i = 15                  closed loop, ki > 0, kd = 0
    pid       (v)    PID design, step                             closed loop, kd > 0

An optional index ``lab.toml`` in the folder names the files and wins over the guess:

    [recordings]
    tap = "tap.toml"
    p_step = "p50.toml"

and may carry a ``[synthetic]`` table: the true parameters that generated synthetic data (the
built-in example recordings use it; the report prints it and compares the fits with it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from jaxcart.errors import UserError

INDEX_NAME = "lab.toml"

#: slot -> (handout part, what the recording is)
SLOTS = {
    "tap": ("i", "tap test, motor unplugged"),
    "p_step": ("ii", "P control, k = 50 V/m, step of 0.4 m"),
    "ramp": ("iii", "open-loop voltage ramp, 0.1 V/s"),
    "p_error": ("iii", "P control, k = 10 V/m, step (steady-state error)"),
    "pi": ("iv", "PI control, k = 10 V/m, k_i = 15 V/(m s), step"),
    "pid": ("v", "PID design, step"),
}
#: The P gain [V/m] of Part (iii)'s steady-state-error experiment.
K_ERROR = 10.0


@dataclass
class Inputs:
    """The recordings found for the lab.

    folder: the data folder; recordings: slot -> Recording (jaxcart.files); how: slot -> how
    it was chosen ("lab.toml" or the rule that matched); unused: (file name, reason) of files
    that went to no slot; synthetic: the [synthetic] table of lab.toml (true parameters of
    synthetic data) or None.
    """

    folder: Path | None
    recordings: dict = field(default_factory=dict)
    how: dict = field(default_factory=dict)
    unused: list = field(default_factory=list)
    synthetic: dict | None = None

    def missing(self) -> list[str]:
        """Slots with no recording (their parts show simulation only)."""
        return [s for s in SLOTS if s not in self.recordings]

    def summary_lines(self) -> list[str]:
        """One line per slot: which file went to which part, or that none did."""
        lines = []
        for slot, (part, what) in SLOTS.items():
            rec = self.recordings.get(slot)
            if rec is None:
                lines.append(f"Part ({part}) {what}: no recording (simulation only)")
            else:
                lines.append(f"Part ({part}) {what}: {Path(rec.path).name} ({self.how[slot]})")
        for name, reason in self.unused:
            lines.append(f"not used: {name} ({reason})")
        return lines


def _read_experiment(path):
    from jaxcart.files import read_experiment

    return check_recording(read_experiment(path))


def check_recording(recording):
    """The lab's own sanity check of a recording before any part computes with it (the file
    readers check the format): finite positions that fit on the track. Returns it."""
    from jaxcart.params import TRACK_LENGTH

    y = np.asarray(recording.position, dtype=float)
    name = recording.path
    if y.size < 2 or not np.all(np.isfinite(y)):
        raise UserError(
            f"{name}: column y needs at least two finite positions [m]; fix the data file"
        )
    span = float(np.ptp(y))
    if span > TRACK_LENGTH:
        unit = " (recorded in mm? divide y by 1000)" if span > 100 * TRACK_LENGTH else ""
        raise UserError(
            f"{name}: the positions y span {span:.4g} m, more than the {TRACK_LENGTH:g} m "
            f"track{unit}; give y in metres"
        )
    return recording


def _load_toml(path: Path) -> dict:
    if path.is_dir():
        raise UserError(f"{path}: a folder, not an experiment file; rename or move it away")
    from hw.expfile import ExpFileError, read_toml

    try:  # the experiment files' own reader: UTF-16, a BOM, a workbook said with the fix
        return read_toml(path)
    except ExpFileError as exc:
        raise UserError(f"{exc}; or move it out of the folder") from None


def guess_slot(recording) -> tuple[str | None, str]:
    """(slot or None, the reason) for one recording, from its kind, controller and input."""
    kind = recording.kind
    if kind == "tap":
        return "tap", "kind = tap"
    if kind == "open_loop":
        inp = (recording.meta or {}).get("input", {})
        if inp.get("kind") == "ramp" or _is_ramp(recording.command):
            return "ramp", "open-loop voltage ramp"
        return None, "open-loop input that is not a ramp"
    ctl = recording.controller
    if ctl is None:
        return None, "closed loop without a [controller] table"
    kp, ki, kd = float(ctl.kp), float(ctl.ki), float(ctl.kd)
    if not _is_step(recording):
        return None, "closed-loop reference that is not a step"
    if kd > 0:
        return "pid", f"PID (kd = {kd:g} > 0), step"
    if ki > 0:
        return "pi", f"PI (ki = {ki:g} > 0, kd = 0), step"
    if math.isclose(kp, K_ERROR, rel_tol=1e-9):
        return "p_error", f"P only with kp = {kp:g} V/m, step"
    return "p_step", f"P only (kp = {kp:g} V/m, ki = kd = 0), step"


def _is_step(recording) -> bool:
    r = recording.reference
    if r is None:
        return False
    r = np.asarray(r, dtype=float)
    return r.size > 1 and float(np.ptp(r[1:])) <= 1e-12 * max(1.0, float(np.abs(r).max()))


def _is_ramp(u) -> bool:
    if u is None:
        return False
    u = np.asarray(u, dtype=float)
    if u.size < 10:
        return False
    slope = np.diff(u)
    return bool(np.all(slope >= 0) and u[-1] > u[0])


def find_inputs(folder) -> Inputs:
    """Read every experiment file of ``folder`` and give each its slot (lab.toml first)."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise UserError(
            f"--data {folder}: a file, not a folder; give the folder that holds the experiment "
            f"files (TOML + data)"
        )
    if not folder.is_dir():
        raise UserError(
            f"--data {folder}: no such folder; give a folder of experiment files (TOML + data)"
        )
    inputs = Inputs(folder=folder)
    index_path = folder / INDEX_NAME
    named = {}
    if index_path.is_file():
        index = _load_toml(index_path)
        table = index.get("recordings", {})
        if not isinstance(table, dict):
            raise UserError(f'{index_path}: [recordings] must be a table of slot = "file.toml"')
        for slot, name in table.items():
            if slot not in SLOTS:
                raise UserError(
                    f"{index_path}: [recordings] {slot} is not a slot of the lab; use one of "
                    f"{', '.join(SLOTS)}"
                )
            path = folder / str(name)
            if path.is_dir():
                raise UserError(
                    f"{index_path}: [recordings] {slot} = {name!r} is a folder; name the "
                    f"experiment file (TOML) inside it"
                )
            if not path.is_file():
                raise UserError(
                    f"{index_path}: [recordings] {slot} = {name!r}: no such file in {folder}"
                )
            named[slot] = path
        synthetic = index.get("synthetic")
        inputs.synthetic = dict(synthetic) if isinstance(synthetic, dict) else None

    for slot, path in named.items():
        inputs.recordings[slot] = _read_experiment(path)
        inputs.how[slot] = f"named in {INDEX_NAME}"

    taken = {p.resolve() for p in named.values()}
    guesses: dict[str, list] = {}
    candidates = sorted(p for p in folder.glob("*.toml") if p.name != INDEX_NAME)
    for path in candidates:
        if path.resolve() in taken:
            continue
        if path.is_dir():
            inputs.unused.append((path.name, "a folder, not an experiment file"))
            continue
        meta = _load_toml(path)
        if "kind" not in meta:
            inputs.unused.append((path.name, "not an experiment file (no kind)"))
            continue
        recording = _read_experiment(path)
        slot, reason = guess_slot(recording)
        if slot is None:
            inputs.unused.append((path.name, reason))
        elif slot in inputs.recordings:
            inputs.unused.append((path.name, f"{slot} is named in {INDEX_NAME}"))
        else:
            guesses.setdefault(slot, []).append((recording, reason))

    for slot, found in guesses.items():
        if len(found) > 1:
            names = ", ".join(Path(r.path).name for r, _ in found)
            raise UserError(
                f"{folder}: {len(found)} recordings fit Part ({SLOTS[slot][0]}) "
                f"{SLOTS[slot][1]} ({names}); name the one to use in {index_path} as "
                f'[recordings] {slot} = "file.toml"'
            )
        inputs.recordings[slot], reason = found[0]
        inputs.how[slot] = f"guessed: {reason}"

    if not inputs.recordings:
        raise UserError(
            f'--data {folder}: no experiment files found (TOML files with kind = "tap", '
            f'"open_loop" or "closed_loop"); see docs/experiment-files.md for the format'
        )
    return inputs
