"""The lab's model of the cart as a value, and what the parts share to simulate with it.

:class:`CartModel` is the best-known cart at one point of the lab (B_eq and f_c with where each
came from); a part that improves it returns a new one (``dataclasses.replace``), and the report
passes it on explicitly. :meth:`CartModel.plant` is the lab's one call into the plant builder.
Every simulation of the report is the exact one (:func:`exact`: hard clip, event-exact
stick-slip, the 1 ms digital loop).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import jaxcart as jc
from jaxcart.effects import effect_of_param
from jaxcart.exact import simulate_exact
from jaxcart.params import Plant
from jaxcart.plantspec import build_plant
from jaxcart.plots import Run
from tuning.lab.context import HANDOUT_B_EQ, V_SAT
from tuning.lab.inputs import SLOTS

#: Horizons [s] of the simulations where no recording sets them, and their steps [m].
HORIZON = {"p_step": 3.0, "ramp": 6.0, "p_error": 5.0, "pi": 10.0, "pid": 3.0}
STEP = {"p_step": 0.4, "p_error": 0.2, "pi": 0.2, "pid": 0.5}
#: e(inf) of a record is the mean error over its last FINAL_WINDOW [s].
FINAL_WINDOW = 0.1


def _effect(param: str):
    """The registered effect that owns parameter ``param`` (names stay in jaxcart.effects)."""
    return effect_of_param(param)


@dataclass(frozen=True)
class CartModel:
    """The best-known cart (motor connected) at one point of the lab.

    B_eq: viscous friction [kg/s]; B_eq_stderr [kg/s] when it was fitted; f_c: Coulomb friction
    [N] (0: none); *_source: where each came from, in the report's words; base: the --plant
    model whose effects carry through (None: the appendix cart).
    """

    B_eq: float = HANDOUT_B_EQ
    B_eq_source: str = "the handout's estimate"
    B_eq_stderr: float | None = None
    f_c: float = 0.0
    f_c_source: str = "none yet (the handout's model)"
    base: Plant | None = None

    @classmethod
    def starting(cls, plant: Plant | None = None) -> CartModel:
        """The model the lab starts from: the handout's, or a --plant file's B_eq and f_c."""
        if plant is None:
            return cls()
        f_c = {}
        if plant.effect(_effect("f_c")) is not None:
            f_c = {"f_c": float(plant.get("f_c")), "f_c_source": "the --plant file"}
        return cls(B_eq=float(plant.B_eq), B_eq_source="the --plant file", base=plant, **f_c)

    def plant(self, *, saturation: bool = True, coulomb: bool = True, **overrides) -> Plant:
        """This cart: appendix values, B_eq and f_c, and the lab's 6 V limit as an amplifier
        saturation (the handout's Simulink block, so that recordings whose files name no
        software limit are simulated as they ran); without the effects the flags turn off."""
        sat, coul = _effect("v_sat"), _effect("f_c")
        values = {"B_eq": self.B_eq}
        if saturation and (self.base is None or self.base.effect(sat) is None):
            values["v_sat"] = V_SAT
        if coulomb and self.f_c > 0:
            values["f_c"] = self.f_c
        if self.base is None:
            return build_plant({**values, **overrides}, where="the lab's plant")
        plant = self.base
        if not coulomb and plant.effect(coul) is not None:
            kept = tuple(e for e in plant.effects if not isinstance(e, coul))
            plant = dataclasses.replace(plant, effects=kept)
        values = {**values, **overrides}
        return build_plant(values, base=plant, check=False, where="the lab's plant")

    def for_recording(self, rec, **flags) -> Plant:
        """:meth:`plant` with what the recording's file overrides (a recording may change M)."""
        plant = self.plant(**flags)
        return rec.plant(plant) if rec is not None and rec.plant_overrides else plant


# ---------------------------------------------------------------- simulations


def exact(plant, controller, experiment):
    """The exact simulator's response (:func:`jaxcart.exact.simulate_exact`)."""
    return simulate_exact(plant, controller, experiment)


def no_limit(controller):
    return dataclasses.replace(controller, v_limit=math.inf)


def crop(time, *arrays, horizon):
    keep = np.asarray(time) <= horizon + 1e-9
    return [np.asarray(time)[keep]] + [None if a is None else np.asarray(a)[keep] for a in arrays]


def final_error(time, error, window=None) -> float:
    """e(inf) from a record [m]: the mean error over its last ``window`` seconds."""
    window = FINAL_WINDOW if window is None else window
    time, error = np.asarray(time), np.asarray(error)
    return float(np.mean(error[time >= time[-1] - window]))


def controller_of(rec, default):
    """The recording's controller, or ``default`` where there is no recording or none in it."""
    return rec.controller if rec is not None and rec.controller is not None else default


def experiment_of(rec, slot):
    """The recording's experiment, or the handout's for ``slot`` where there is no recording."""
    if rec is not None:
        return rec.experiment
    if slot == "ramp":
        return jc.voltage_ramp(0.1, horizon=HORIZON[slot])
    return jc.step(STEP[slot], horizon=HORIZON[slot])


def source_name(rec) -> str:
    """The recording's file name, or "simulation only"."""
    return "simulation only" if rec is None else Path(rec.path).name


def render_source(doc, rec, slot) -> None:
    """The line naming a part's recording (or the note that there is none)."""
    part, what = SLOTS[slot]
    if rec is None:
        doc.note(f"No recording for Part ({part}) ({what}): this section shows simulation only.")
        return
    desc = rec.meta.get("description")
    doc.paragraph(f"Recording: `{Path(rec.path).name}`" + (f" ({desc})." if desc else "."))


def run(label, time, position, voltage=None, role="simulation"):
    """A :class:`jaxcart.plots.Run` from arrays."""
    return Run(
        label,
        np.asarray(time),
        np.asarray(position),
        None if voltage is None else np.asarray(voltage),
        role,
    )


def seconds(x) -> str:
    """A time [s] for a table; a run that never settles says so instead of "inf"."""
    return f"{x:.3f}" if math.isfinite(x) else "does not settle within the horizon"
