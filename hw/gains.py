"""Gains files: every setting of the canonical PID in one JSON file, plus how it was obtained.

Standard library and numpy only (hw/ never imports jax). A gains file records the whole
controller (docs/design.md, "The control law"), so the simulator, the hardware loop and any
independent check run exactly the same one::

    {
      "format": "jaxcart-gains",
      "version": 1,
      "controller": {"kp": 120.9, "ki": 1.67, "kd": 4.1, "tau": 0.01, "v_limit": 6.0,
                     "kb": 1.0, "sample_time": 0.001, "derivative_on": "error",
                     "anti_windup": "none"},
      "units": {"kp": "V/m", ...},
      "date": "2025-01-01T12:00:00+00:00",
      ...metadata (metrics, plant, spec, ...)
    }

``v_limit`` = inf (no software limit) is written as null and read back as ``math.inf``; the
string "inf" is accepted too. Every field of the controller is required when reading: a file
that leaves one out would make the hardware silently run a default the tuner never saw.

>>> import tempfile, os
>>> from hw.control_law import PID
>>> path = os.path.join(tempfile.mkdtemp(), "gains.json")
>>> _ = write_gains(path, PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0), note="handout")
>>> read_gains(path).kp
40.0
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
from pathlib import Path

from hw.atomicio import OutputError, write_text
from hw.control_law import ANTI_WINDUP_MODES, DERIVATIVE_MODES, PID, setting_problem
from hw.control_law import UNITS as CONTROLLER_UNITS
from hw.jsonio import to_jsonable
from hw.predicted import problem_of
from hw.stepinfo import spec_problem

FORMAT = "jaxcart-gains"
VERSION = 1
#: Units of the controller fields (written into the file for the reader's benefit).
UNITS = dict(CONTROLLER_UNITS)
CONTROLLER_FIELDS = tuple(f.name for f in dataclasses.fields(PID))
_CHOICES = {"derivative_on": DERIVATIVE_MODES, "anti_windup": ANTI_WINDUP_MODES}
_RESERVED = ("format", "version", "controller", "units")


class GainsFileError(ValueError):
    """A gains file that cannot be read or written; ``path`` and ``field`` name the culprit."""

    def __init__(self, message: str, *, path=None, field: str | None = None):
        self.path = None if path is None else str(path)
        self.field = field
        where = f"{self.path}: " if self.path else ""
        what = f"{field}: " if field else ""
        super().__init__(f"{where}{what}{message}")


def write_gains(path, pid: PID, *, force: bool = False, **metadata) -> Path:
    """Write ``pid`` (every setting) and ``metadata`` to the JSON gains file ``path``.

    Refuses to replace an existing file unless ``force``. Metadata values may be numbers,
    strings, lists, dicts, numpy values, named tuples (``_asdict``) or dataclasses; non-finite
    numbers are written as the strings "inf", "-inf", "nan" (JSON has no such numbers).
    A "date" (UTC, ISO 8601) is added unless given. Returns the path written.
    """
    path = Path(path)
    if not isinstance(pid, PID):
        raise GainsFileError(f"expected a PID, got {type(pid).__name__}", path=path)
    for key in metadata:
        if key in _RESERVED:
            raise GainsFileError(
                f"metadata key {key!r} is reserved; choose another name", path=path, field=key
            )
    controller = pid.to_dict()
    for name in CONTROLLER_FIELDS:
        # The checks of read_gains: never write a file that cannot be read back.
        value = _field(path, name, controller[name])
        controller[name] = None if value == math.inf else value
    document = {
        "format": FORMAT,
        "version": VERSION,
        "controller": controller,
        "units": dict(UNITS),
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }
    for key, value in metadata.items():
        try:
            document[key] = to_jsonable(value)
        except TypeError as exc:
            raise GainsFileError(f"metadata {key}: {exc}", path=path) from None
    text = json.dumps(document, indent=2, allow_nan=False) + "\n"
    if path.exists() and not force:
        raise GainsFileError("the file exists; pass force=True (--force) to replace it", path=path)

    try:  # beside the target, then renamed: a crash or a full disk never leaves half a file
        return write_text(path, text, force=force)
    except OutputError as exc:
        raise GainsFileError(str(exc)) from None  # the message names the file


def read_gains(path) -> PID:
    """The :class:`hw.control_law.PID` recorded in the gains file ``path``.

    Raises :class:`GainsFileError` (a ValueError) naming the file and the field for a file that
    is missing or not JSON, a controller field that is missing, unknown, of the wrong type or out
    of range.
    """
    return read_gains_file(path)[0]


def read_gains_file(path) -> tuple[PID, dict]:
    """(PID, metadata) of the gains file ``path`` (metadata: every top-level key but the
    controller, format, version and units)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise GainsFileError("no such file", path=path) from None
    except OSError as exc:
        raise GainsFileError(f"cannot read it ({exc.strerror})", path=path) from None
    try:
        document = json.loads(text, parse_constant=_reject_constant)
    except (json.JSONDecodeError, ValueError) as exc:
        raise GainsFileError(f"not a JSON gains file ({exc})", path=path) from None
    if not isinstance(document, dict):
        raise GainsFileError("not a gains file: expected a JSON object", path=path)
    if document.get("format", FORMAT) != FORMAT:
        raise GainsFileError(
            f"format = {document['format']!r}: expected {FORMAT!r}", path=path, field="format"
        )
    version = document.get("version", VERSION)
    if version != VERSION:
        raise GainsFileError(
            f"version = {version!r}: this reader knows version {VERSION}",
            path=path,
            field="version",
        )
    table = document.get("controller")
    if not isinstance(table, dict):
        raise GainsFileError(
            'missing the "controller" object with the PID settings', path=path, field="controller"
        )
    unknown = sorted(set(table) - set(CONTROLLER_FIELDS))
    if unknown:
        raise GainsFileError(
            f"unknown field(s) {', '.join(unknown)}; known: {', '.join(CONTROLLER_FIELDS)}",
            path=path,
            field="controller." + unknown[0],
        )
    missing = [name for name in CONTROLLER_FIELDS if name not in table]
    if missing:
        raise GainsFileError(
            f"missing field(s) {', '.join(missing)}: a gains file records every setting",
            path=path,
            field="controller." + missing[0],
        )
    values = {name: _field(path, name, table[name]) for name in CONTROLLER_FIELDS}
    try:
        pid = PID(**values)
    except ValueError as exc:
        raise GainsFileError(str(exc), path=path, field="controller") from None
    metadata = {k: v for k, v in document.items() if k not in _RESERVED}
    # Read before the run: after it, the recording would be judged by what is wrong here.
    wrong = problem_of(metadata["prediction"]) if "prediction" in metadata else None
    if wrong is not None:
        raise GainsFileError(f"{wrong[1]} (or delete the prediction)", path=path, field=wrong[0])
    wrong = spec_problem(metadata["spec"]) if "spec" in metadata else None
    if wrong is not None:
        raise GainsFileError(f"{wrong[1]} (or delete the spec)", path=path, field=wrong[0])
    return pid, metadata


def _field(path, name, value):
    field = f"controller.{name}"
    if name in _CHOICES:
        if value not in _CHOICES[name]:
            raise GainsFileError(
                f"{value!r}: use one of {', '.join(_CHOICES[name])}", path=path, field=field
            )
        return value
    if name == "v_limit" and (value is None or value == "inf" or value == math.inf):
        return math.inf
    problem = setting_problem(name, value)  # the one rule of a PID setting (hw.control_law)
    if problem:
        hint = ' (null or "inf" for no limit)' if name == "v_limit" else ""
        raise GainsFileError(problem.replace(" (inf for no limit)", hint), path=path, field=field)
    return float(value)


def _reject_constant(name):
    # json.loads would accept NaN/Infinity, which are not JSON; say where instead.
    raise ValueError(f'{name} is not a JSON number; write null or "inf" for v_limit')


__all__ = [
    "GainsFileError",
    "write_gains",
    "read_gains",
    "read_gains_file",
    "FORMAT",
    "VERSION",
    "CONTROLLER_FIELDS",
    "UNITS",
]
