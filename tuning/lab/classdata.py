"""A synthetic class: one folder per student, each made by the built-in recordings' generator
(:mod:`tuning.lab.data`, :mod:`jaxcart.synthetic`) on a cart of its own.

Every student runs the handout's six experiments (the specs of :data:`tuning.lab.data.SPECS`:
tap, P 50 step, 0.1 V/s ramp, P 10 step, PI step, the pre-lab's PID step) on a cart that
differs from the others' in viscous friction B_eq [kg/s] and Coulomb friction f_c [N], drawn
uniformly from :data:`B_EQ_RANGE` and :data:`F_C_RANGE` (around the built-in cart's 4.6 kg/s
and 0.45 N). The mass, 6 V saturation and encoder are the built-in cart's. Each folder holds
the experiment files (TOML + CSV) and a ``lab.toml`` that names them and carries the student's
true cart in ``[synthetic]``, which the report compares its fits with.

    python -m tuning.lab.classdata CLASS_DIR [N]     # an example class for `jaxcart class`

>>> carts = generate_class("/tmp/class", 8, horizons=SHORT)   # doctest: +SKIP
>>> sorted(carts)[:2]                                         # doctest: +SKIP
['student-01', 'student-02']
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np

import jaxcart as jc
from jaxcart.errors import UserError
from jaxcart.plantspec import build_plant
from jaxcart.synthetic import make_recording, make_tap_recording, write_recording
from tuning.lab import data

#: Viscous friction B_eq [kg/s] and Coulomb friction f_c [N] of the class's carts (uniform).
B_EQ_RANGE = (3.5, 6.0)
F_C_RANGE = (0.3, 0.6)
#: Shorter horizons [s] per slot (a quicker class; see :func:`write_student`): the ramp still
#: breaks away (at f_c / (gamma 0.1 V/s) <= 3.5 s for f_c <= 0.6 N), the P 10 and PI steps
#: still come near rest.
SHORT = {"ramp": 4.5, "p_error": 4.0, "pi": 4.0}


def student_carts(n: int, *, seed: int = 0) -> dict[str, dict]:
    """``n`` students' true carts: {"student-01": {"B_eq": ..., "f_c": ...}, ...} (SI units),
    drawn from ``seed``."""
    if n < 1:
        raise UserError(f"a class of {n} students: give at least 1")
    rng = np.random.default_rng(seed)
    width = len(str(n))
    return {
        f"student-{k + 1:0{max(2, width)}d}": {
            "B_eq": round(float(rng.uniform(*B_EQ_RANGE)), 3),
            "f_c": round(float(rng.uniform(*F_C_RANGE)), 3),
        }
        for k in range(n)
    }


def write_student(folder, cart: dict, *, seed: int, horizons: dict | None = None) -> list[Path]:
    """One student's folder: the six experiments on ``cart`` ({"B_eq", "f_c"}, SI units) and
    lab.toml. horizons: {slot: seconds} replacing the built-in horizons (e.g. :data:`SHORT`);
    seed: the encoder phase. Refuses to write into a folder that holds files."""
    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        raise UserError(f"{folder}: the folder holds files; give a new folder for the student")
    folder.mkdir(parents=True, exist_ok=True)
    truth = {**data.TRUE, **cart}
    written = []
    with jax.enable_x64(True):  # references and ramps in float64, as the built-in data
        for spec in data.SPECS:
            if horizons and spec.slot in horizons:
                spec = dataclasses.replace(spec, horizon=float(horizons[spec.slot]))
            rec = _make(spec, truth, seed)
            written.append(write_recording(rec, folder / f"{spec.stem}.toml"))
    index = folder / "lab.toml"
    index.write_text(_index(truth, seed))
    return [*written, index]


def generate_class(
    folder, n: int = 8, *, seed: int = 0, horizons: dict | None = None
) -> dict[str, dict]:
    """A class of ``n`` students in ``folder`` (one sub-folder each, see :func:`write_student`);
    returns {student: true cart}."""
    carts = student_carts(n, seed=seed)
    for k, (name, cart) in enumerate(carts.items()):
        write_student(Path(folder) / name, cart, seed=seed * 1000 + k, horizons=horizons)
    return carts


def _make(spec, truth: dict, seed: int):
    """The recording of one spec on the cart ``truth`` (as :func:`tuning.lab.data.make` makes
    the built-in ones on the built-in cart)."""
    values = {name: truth[name] for name in ("M", "B_eq", "f_c")}
    q = truth[data.ENCODER_PARAM]
    if spec.kind == "tap":
        cart = build_plant(values, motor_connected=False, where="a synthetic student's tap")
        tap = {k: v for k, v in data.TAP.items() if k != "horizon"}
        return make_tap_recording(cart, **tap, horizon=spec.horizon, quantization=q, seed=seed)
    cart = build_plant({**values, "v_sat": truth["v_sat"]}, where="a synthetic student's cart")
    if spec.kind == "open_loop":
        experiment = jc.voltage_ramp(spec.ramp, horizon=spec.horizon)
        return make_recording(cart, None, experiment, quantization=q, seed=seed)
    experiment = jc.step(spec.step, horizon=spec.horizon)
    return make_recording(cart, jc.PID(**spec.controller), experiment, quantization=q, seed=seed)


def _index(truth: dict, seed: int) -> str:
    lines = ["# Which file is which part (jaxcart lab reads this first).", "[recordings]"]
    lines += [f'{spec.slot} = "{spec.stem}.toml"' for spec in data.SPECS]
    lines += [
        "",
        "# Synthetic: the true cart that made these recordings (SI units).",
        "[synthetic]",
    ]
    lines.append('made_by = "tuning.lab.classdata (exact simulator + encoder quantization)"')
    lines.append(f"seed = {seed}")
    lines += [f"{name} = {float(truth[name])!r}" for name in ("M", "B_eq", "f_c", "v_sat")]
    lines.append(f"{data.ENCODER_PARAM} = {float(truth[data.ENCODER_PARAM])!r}")
    lines += [f"pid_{k} = {float(v)!r}" for k, v in data.PID_DESIGN.items()]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:  # pragma: no cover - run by hand, see the module docstring

    args = sys.argv[1:] if argv is None else argv
    if not args or len(args) > 2:
        print("usage: python -m tuning.lab.classdata CLASS_DIR [N]", file=sys.stderr)
        return 2
    n = int(args[1]) if len(args) > 1 else 8
    try:
        carts = generate_class(args[0], n)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for name, cart in carts.items():
        print(f"{name}: B_eq = {cart['B_eq']:g} kg/s, f_c = {cart['f_c']:g} N")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
