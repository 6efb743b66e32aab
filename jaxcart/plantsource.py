"""Where a ``--plant FILE`` option's plant comes from: a plant file (:mod:`jaxcart.plantspec`)
or an experiment file whose [plant] table applies (:mod:`jaxcart.files`).

Its own module because it needs both: the plant spec must not import the experiment files,
which build their plants through it.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from jaxcart.errors import UserError
from jaxcart.files import read_experiment
from jaxcart.params import Plant
from jaxcart.plantspec import FORMAT, read_plant_file


def load_plant(path, *, where: str = "--plant") -> Plant:
    """A plant from a plant file, or from an experiment file's [plant] table (its kind's
    nominal plant with those values); the one reader behind every ``--plant FILE`` option."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{where} {path}: no such file; give a plant file (.toml)")
    try:
        head = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except (tomllib.TOMLDecodeError, OSError, UnicodeDecodeError):
        head = {}
    if head.get("format") == FORMAT or path.suffix.lower() != ".toml":
        return read_plant_file(path)[0]
    return read_experiment(path).plant()
