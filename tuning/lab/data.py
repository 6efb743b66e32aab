"""The built-in example recordings of the lab (shipped in ``jaxcart/data/``).

They are synthetic: made once by :func:`generate` with the exact simulator
(:func:`jaxcart.exact.simulate_exact`, event-exact stick-slip and hard clip) through the cart's
encoder (:mod:`jaxcart.synthetic`), from a "true" cart that differs from the handout's model:

    M = 0.94 kg (the appendix's; the cart is weighed in the lab)
    B_eq = 4.6 kg/s (the handout estimates 5.4)
    f_c = 0.45 N Coulomb friction (the handout's model has none)
    6 V amplifier saturation, encoder 2.275e-5 m per count (positions are whole counts)

One recording per item of the handout (horizons as short as the item allows):

    slot     file          experiment
    tap      tap.toml      rest 0.5 s, push 0.1 s to 1.5 m/s, coast, motor unplugged; 2.5 s
    p_step   p50.toml      P, k = 50 V/m, 6 V software limit, step 0.4 m; 3 s
    ramp     ramp.toml     open-loop voltage ramp 0.1 V/s; 6 s
    p_error  p10.toml      P, k = 10 V/m, step 0.2 m; 8 s
    pi       pi.toml       PI, k = 10 V/m, k_i = 15 V/(m s), step 0.2 m; 10 s
    pid      pid.toml      the pre-lab's tuned PID kp = 250 V/m, kd = 5.8565 V s/m,
                           ki = 0.94131 V/(m s), tau = 0.01 s, 6 V software limit, step 0.5 m; 3 s

The P 10 recording is long enough for the cart to come to rest: its two closed-loop poles are
real (-1.63 and -9.85 1/s), so it creeps towards the edge of the Coulomb dead band with a time
constant of 0.61 s and is 0.06 mm short of it at 5 s, 0.0004 mm (1/50 count) at 8 s.

The Part (v) gains are the PID that ``jaxcart lab`` tuned in its pre-lab when the data were
made (rounded to 4 digits), so Part (v) compares the design with "its" run on the cart; they
are frozen here because the tuner may change, and the report says when its tuned gains differ
from the recording's. The index ``lab.toml`` maps slots to files and carries the truth in
``[synthetic]``, which the report prints and compares its fits with.

The CSV files are compact but exact: t with 3 decimals, positions as whole counts written with
8 decimals (q = 2.275e-5 m has 8, so every count is written exactly), voltages with 12
significant digits. Regenerating with the same seed gives identical files (tested):

    python -c "import sys, tuning.lab.data as d; sys.argv.append('--force'); d.main()"
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

import jaxcart as jc
from hw.atomicio import all_or_none, exists_message, write_bytes
from jaxcart.effects import Quantization
from jaxcart.errors import UserError
from jaxcart.files import BUILTIN_DATA
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.plantspec import build_plant
from jaxcart.synthetic import make_recording, make_tap_recording

#: The name of the encoder's count size [m/count] (the encoder effect's parameter): its key in
#: TRUE, in lab.toml's [synthetic] table and in results.json.
ENCODER_PARAM = Quantization.params[0].name
#: The true cart of the built-in recordings (SI units: kg, kg/s, N, V, m).
TRUE = {"M": 0.94, "B_eq": 4.6, "f_c": 0.45, "v_sat": 6.0, ENCODER_PARAM: ENCODER_RESOLUTION}
#: Seed of the encoder phase (the only random draw; there is no added noise).
SEED = 364
#: Part (v)'s gains, the pre-lab's tuned PID (frozen): kp [V/m], kd [V s/m], ki [V/(m s)].
PID_DESIGN = {"kp": 250.0, "kd": 5.8565, "ki": 0.94131}
_UNITS = ("V/m", "V s/m", "V/(m s)")
#: Tap test: resting time, push duration [s], speed after the push [m/s], length [s].
TAP = {"rest": 0.5, "push_time": 0.1, "speed": 1.5, "horizon": 2.5}


@dataclass(frozen=True)
class Spec:
    """One built-in recording: slot, file stem, what it is, and how to make it."""

    slot: str
    stem: str
    description: str
    kind: str
    horizon: float  # [s]
    controller: dict | None = None  # PID settings
    step: float | None = None  # closed-loop step [m]
    ramp: float | None = None  # open-loop ramp [V/s]


SPECS = (
    Spec(
        "tap", "tap", "Part (i): tap test, motor unplugged, coasting to rest", "tap", TAP["horizon"]
    ),
    Spec(
        "p_step",
        "p50",
        "Part (ii): P control k = 50 V/m, 6 V software limit, step 0.4 m",
        "closed_loop",
        3.0,
        {"kp": 50.0, "v_limit": 6.0},
        step=0.4,
    ),
    Spec("ramp", "ramp", "Part (iii): open-loop voltage ramp 0.1 V/s", "open_loop", 6.0, ramp=0.1),
    Spec(
        "p_error",
        "p10",
        "Part (iii): P control k = 10 V/m, step 0.2 m (steady-state error)",
        "closed_loop",
        8.0,
        {"kp": 10.0},
        step=0.2,
    ),
    Spec(
        "pi",
        "pi",
        "Part (iv): PI control k = 10 V/m, k_i = 15 V/(m s), step 0.2 m",
        "closed_loop",
        10.0,
        {"kp": 10.0, "ki": 15.0},
        step=0.2,
    ),
    Spec(
        "pid",
        "pid",
        "Part (v): the pre-lab's tuned PID "
        + ", ".join(
            f"{k} = {v:g} {u}" for (k, v), u in zip(PID_DESIGN.items(), _UNITS, strict=True)
        )
        + ", 6 V software limit, step 0.5 m",
        "closed_loop",
        3.0,
        {**PID_DESIGN, "v_limit": 6.0},
        step=0.5,
    ),
)


def builtin_dir() -> Path:
    """The folder of the built-in recordings inside the installed package."""
    return BUILTIN_DATA


def copy_examples(folder, *, force: bool = False) -> list[Path]:
    """Copy the built-in recordings (every experiment file, its CSV, and lab.toml) into
    ``folder`` (made if missing), each file atomically; an existing file is refused before
    anything is written, unless ``force``. Returns the paths written."""
    folder = Path(folder)
    sources = sorted(p for p in builtin_dir().iterdir() if p.suffix in (".toml", ".csv"))
    targets = [folder / p.name for p in sources]
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{folder} is a file, not a folder; give a folder name")
    for target in targets:
        if target.exists() and not force:
            raise UserError(
                exists_message(target) + " (nothing was copied; your own files are never "
                "replaced without --force)"
            )
    with all_or_none(*targets):  # all of them, or none (a full disk: an OutputError)
        for source, target in zip(sources, targets, strict=True):
            write_bytes(target, source.read_bytes(), force=force)
    return targets


def true_plant(*, tap: bool = False):
    """The true cart of the built-in data (motor unplugged for the tap)."""
    values = {n: TRUE[n] for n in ("M", "B_eq", "f_c")}
    if tap:
        return build_plant(values, motor_connected=False, where="the built-in tap's cart")
    return build_plant({**values, "v_sat": TRUE["v_sat"]}, where="the built-in cart")


def make(spec: Spec, *, seed: int = SEED):
    """The synthetic recording of one spec (a :class:`jaxcart.synthetic.SyntheticRecording`)."""
    q = TRUE[ENCODER_PARAM]
    if spec.kind == "tap":
        return make_tap_recording(
            true_plant(tap=True),
            speed=TAP["speed"],
            rest=TAP["rest"],
            push_time=TAP["push_time"],
            horizon=spec.horizon,
            quantization=q,
            seed=seed,
        )
    if spec.kind == "open_loop":
        return make_recording(
            true_plant(),
            None,
            jc.voltage_ramp(spec.ramp, horizon=spec.horizon),
            quantization=q,
            seed=seed,
        )
    controller = jc.PID(**spec.controller)
    return make_recording(
        true_plant(),
        controller,
        jc.step(spec.step, horizon=spec.horizon),
        quantization=q,
        seed=seed,
    )


def generate(folder, *, force: bool = False, seed: int = SEED) -> list[Path]:
    """Write the built-in recordings (TOML + CSV each) and the index lab.toml into ``folder``.

    Refuses to overwrite an existing file unless ``force``. Returns the paths written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    outputs = {}
    with jax.enable_x64(True):  # the references and ramps in float64, whatever the caller set
        for spec in SPECS:
            rec = make(spec, seed=seed)
            outputs[folder / f"{spec.stem}.toml"] = _toml(spec, rec)
            outputs[folder / f"{spec.stem}.csv"] = _csv(spec, rec)
    outputs[folder / "lab.toml"] = _index()
    for path in outputs:
        if path.exists() and not force:
            raise UserError(f"{path} exists; pass force=True to regenerate the built-in data")
    for path, text in outputs.items():
        path.write_text(text)
    return list(outputs)


# ---------------------------------------------------------------- writing


def _csv(spec: Spec, rec) -> str:
    y = np.asarray(rec.position, dtype=float)
    counts = np.rint(y / TRUE[ENCODER_PARAM])
    if np.max(np.abs(counts * TRUE[ENCODER_PARAM] - y)) > 1e-12:
        raise AssertionError("positions are not whole encoder counts")
    t = np.arange(y.size) * float(rec.sample_time)
    columns = [("t", [f"{x:.3f}" for x in t]), ("y", [_count(c) for c in counts])]
    if spec.kind == "closed_loop":
        columns.append(("v", [_volt(x) for x in np.asarray(rec.command, dtype=float)]))
    header = ",".join(name for name, _ in columns)
    rows = (",".join(values) for values in zip(*(v for _, v in columns), strict=True))
    return header + "\n" + "\n".join(rows) + "\n"


def _count(c: float) -> str:
    """A whole number of counts as metres, exactly (q has 8 decimals)."""
    scaled = int(c) * 2275  # q = 2275e-8 m
    sign = "-" if scaled < 0 else ""
    scaled = abs(scaled)
    return f"{sign}{scaled // 10**8}.{scaled % 10**8:08d}"


def _volt(x: float) -> str:
    text = f"{x:.12g}"
    return "0" if text in ("0", "-0") else text


def _toml(spec: Spec, rec) -> str:
    truth = ", ".join(f"{k} = {TRUE[k]:g}" for k in ("M", "B_eq", "f_c", "v_sat"))
    lines = [
        f"# {spec.description}.",
        "# Synthetic: exact simulator + encoder (jaxcart built-in example; tuning/lab/data.py).",
        f'description = "{spec.description} (synthetic; truth: {truth}, encoder '
        f'{TRUE[ENCODER_PARAM]:g} m)"',
        f'kind = "{spec.kind}"',
        f"sample_time = {float(rec.sample_time)!r}",
        f'data = "{spec.stem}.csv"   # columns t [s], y [m]'
        + (", v [V] (the command the software sent)" if spec.kind == "closed_loop" else ""),
    ]
    if spec.kind == "tap":
        lines += ["", "[tap]", "motor_connected = false"]
    elif spec.kind == "open_loop":
        lines += ["", "[input]", 'kind = "ramp"', f"slope = {spec.ramp!r}   # [V/s]"]
    else:
        lines += ["", "[controller]"]
        for key, value in spec.controller.items():
            unit = {"kp": "V/m", "ki": "V/(m s)", "kd": "V s/m", "v_limit": "V"}[key]
            note = ", the software's own limit block" if key == "v_limit" else ""
            lines.append(f"{key} = {float(value)!r}   # [{unit}{note}]")
        lines += ["", "[reference]", 'kind = "step"', f"amplitude = {spec.step!r}   # [m]"]
    return "\n".join(lines) + "\n"


def _index() -> str:
    lines = [
        "# The lab's recordings: which file is which part (jaxcart lab reads this first).",
        "[recordings]",
    ]
    lines += [f'{spec.slot} = "{spec.stem}.toml"' for spec in SPECS]
    lines += [
        "",
        "# The built-in recordings are synthetic: the true cart that made them.",
        "[synthetic]",
        'made_by = "tuning.lab.data.generate (exact simulator + encoder quantization)"',
        f"seed = {SEED}",
        f"M = {TRUE['M']!r}            # [kg]",
        f"B_eq = {TRUE['B_eq']!r}           # [kg/s]",
        f"f_c = {TRUE['f_c']!r}           # Coulomb friction [N]",
        f"v_sat = {TRUE['v_sat']!r}          # amplifier saturation [V]",
        f"{ENCODER_PARAM} = {TRUE[ENCODER_PARAM]!r}  # encoder [m/count]",
        f"pid_kp = {PID_DESIGN['kp']!r}       # Part (v)'s gains (the pre-lab's tuned PID) [V/m]",
        f"pid_kd = {PID_DESIGN['kd']!r}         # [V s/m]",
        f"pid_ki = {PID_DESIGN['ki']!r}         # [V/(m s)]",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:  # pragma: no cover - run by hand, see the module docstring

    folder = builtin_dir()
    paths = generate(folder, force="--force" in sys.argv)
    total = sum(p.stat().st_size for p in paths)
    print(f"wrote {len(paths)} files to {folder} ({total / 1e3:.0f} kB)")


if __name__ == "__main__":  # pragma: no cover
    main()
