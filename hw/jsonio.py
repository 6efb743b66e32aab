"""The project's one JSON writer (numpy and the standard library only, so hw/ can use it).

Every command and report writes JSON through :func:`write_json`: numpy values, named tuples,
dataclasses and paths become plain JSON; non-finite floats become the strings "inf", "-inf"
and "nan" (JSON has no such numbers); a file is written beside its target and renamed
(:mod:`hw.atomicio`), so a crash or a full disk never leaves half a file; an existing file is
kept unless ``force``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

from hw.atomicio import OutputError, exists_message, write_text


class JsonFileExists(OutputError):
    """The target exists and ``force`` was not given."""


def to_jsonable(value):
    """Plain JSON data from numbers, numpy values, named tuples, dataclasses, paths."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if hasattr(value, "_asdict"):
        return to_jsonable(value._asdict())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_jsonable({f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
    if isinstance(value, list | tuple | set | frozenset):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray) or hasattr(value, "__array__") and hasattr(value, "shape"):
        return to_jsonable(np.asarray(value).tolist())
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        value = float(value)
        if math.isfinite(value):
            return value
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if value is None or isinstance(value, str):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"a {type(value).__name__} is not JSON-serializable")


def dumps(document) -> str:
    """The document as indented JSON text (ending in a newline)."""
    return json.dumps(to_jsonable(document), indent=2, allow_nan=False) + "\n"


def write_json(path, document, *, force: bool = False) -> Path | None:
    """Write ``document`` to ``path`` ("-": standard output); returns the path written.

    Raises :class:`JsonFileExists` if the file exists and not ``force``, an
    :class:`hw.atomicio.OutputError` (one line: cause and fix) if it cannot be written."""
    text = dumps(document)
    if str(path) == "-":
        sys.stdout.write(text)
        return None
    path = Path(path)
    if path.exists() and not force:
        raise JsonFileExists(exists_message(path))
    return write_text(path, text, force=force)
