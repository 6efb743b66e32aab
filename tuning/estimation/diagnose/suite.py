"""The concealed-effect suite: each effect plain and concealed (brief, masked by integral action,
without a column v, combined with a second effect), identifiable stiction (a late breakaway on
a voltage ramp, stick-slip hunting under PI, also strong: static friction 2.2-2.5 times
kinetic at 2-2.2 N), several recordings of one cart whose drive differs from run to run,
friction and a dead band that differ by direction, a voltage offset (in closed loop a tie with a
tilt), a tilt told from it by a tap, Stribeck friction,
friction that varies along the track (no candidate: "not explained" is the right answer; with
``--curve`` and runs that cover the track, a curve of the position),
clean recordings and parameter errors; and its score table. What counts as right is each
case's ``rule`` (:data:`RULES`).

Two generators make the recordings (:data:`GENERATORS`): "exact", jaxcart's own exact
simulator through the encoder (:mod:`jaxcart.synthetic`), where the model class holds the truth
exactly (the "inverse crime"); and "independent", :mod:`tuning.verification`, a simulator
written apart from jaxcart (its own integrator, Karnopp friction with a zero-velocity band and
control loop) with what real recordings carry (:data:`tuning.verification.REALISTIC`: the
controller reading whole counts, the encoder's phase, sampling jitter, drift, a 0.1 ms
amplifier lag, run-to-run drive variation, a hand's push of varying shape). A case of one
recording has the cart's own drive; each of several runs of one cart draws its drive anew
(gain 1 %, limits 3 %), and is judged against the drive it had. A case is made by both
generators unless it says otherwise (``generators``); ``independent`` holds what differs on
independent data (more truth the library lacks, another rule), each with its reason.

    python -m tuning.estimation.diagnose.suite [--fast] [--only NAME,...]
        [--generator exact|independent|both]                    (or: jaxcart diagnose --suite)

Every case is written as an experiment file (TOML + CSV) in a temporary folder and read back,
so the diagnosis sees exactly what a user's file gives it (a case "without v" has its column v
dropped); a case of several runs is diagnosed jointly, as ``jaxcart diagnose A.toml B.toml``.
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import jaxcart as jc
from hw.jsonio import write_json
from jaxcart.cache import enable_persistent_cache
from jaxcart.effects import (
    Coulomb,
    CoulombAsymmetry,
    CurrentLimit,
    Deadzone,
    DeadzoneAsymmetry,
    Delay,
    Saturation,
    Spring,
    Stiction,
    Stribeck,
    Tilt,
    ViscousAsymmetry,
    VoltageOffset,
)
from jaxcart.files import read_experiment
from jaxcart.parallel import use_cpu_devices
from jaxcart.plantspec import build_plant
from jaxcart.synthetic import make_recording, make_tap_recording, write_recording
from jaxcart.workers import Helpers
from tuning.estimation.diagnose import diagnose
from tuning.estimation.diagnose.structures import PER_RUN, per_run_params
from tuning.verification import REALISTIC, TrueCart
from tuning.verification import experiments as ex
from tuning.verification import make_recording as make_independent_recording

#: What counts as right, per case (:func:`judge`). "names": the named effects are the expected
#: ones, or the expected ones are among the structures said to fit equally well (a tie said
#: is not wrong); "exact": the named effects are exactly the expected ones, nothing more
#: (Coulomb friction under a PI loop must not come out with a deadzone beside it);
#: "nothing": no effect named, no parameter corrected; "corrected": no effect named, a
#: parameter corrected; "per_run": the expected effects named, the chosen structure frees the
#: drive's limit per run (its parts include core.PER_RUN) and each driven run's own limit lies
#: within PER_RUN_TOLERANCE of its truth; "shared": the expected effects named and the drive's
#: limit shared (one cart, one drive: freeing it per run is a false alarm); "not_explained":
#: the recording is said to be not explained and a suggestion names ``case.suggest`` (the
#: truth is no candidate, e.g. friction that varies along the track); "curve": friction read as a
#: curve (the suite run with ``--curve``) of the truth's shape is named: of the position where
#: the truth's friction varies along the track, within CURVE_TOLERANCE of it at the knots it
#: fitted; else of the speed, within CURVE_TOLERANCE of the truth's at every
#: entry from 80 mm/s on that the recordings determine.
RULES = ("names", "exact", "nothing", "corrected", "per_run", "shared", "not_explained", "curve")
#: The discovered curve is right within this much of the truth's friction [N].
CURVE_TOLERANCE = 0.05
#: A run's own drive limit is right within this share of its truth.
PER_RUN_TOLERANCE = 0.05
#: The generators of the recordings (module docstring).
GENERATORS = ("exact", "independent")
#: The kinds of recording a case makes (:class:`Case`).
KINDS = ("step", "ramp", "square", "out_back", "open_ramp", "tap")
#: What a case's ``independent`` may change for the independent generator.
INDEPENDENT_KEYS = ("truth", "rule", "expect", "also", "suggest", "artefacts", "why")


@dataclass(frozen=True)
class Case:
    """One case: a truth (plant values, SI), the recording(s) made of it, and what counts as
    the right answer (``rule``, one of :data:`RULES`, with ``expect``).

    kind: "step" | "ramp" | "square" | "out_back" (closed loop, reference amplitude [m], slope
    [m/s], a square wave between 0 and ``amplitude`` of ``period`` [s], or out to the amplitude
    and back to minus half of it at half the horizon, so the cart moves both ways) |
    "open_ramp" (open-loop voltage ramp of ``rate`` [V/s]) | "tap" (motor unplugged); horizon
    [s] (None: the kind's default);
    kp [V/m], ki [V/(m s)], kd [V s/m], v_limit [V]: the PID; drop_v: the column v dropped
    from the file; drop: other columns dropped (("y",): the position given by the error e
    and the reference). ``runs``: several recordings of one cart, each a dict of the fields
    that differ from the case's (its "truth" entries update the case's truth).
    ``generators``: which make it; ``independent``: what differs on the independent
    generator's data, keys :data:`INDEPENDENT_KEYS`: "truth" (values added, in
    :class:`tuning.verification.TrueCart`'s names), "rule", "expect", "also" (other sets of
    effects that name that truth as rightly, rule "names"), "suggest", "artefacts" (changes to
    REALISTIC) and "why" (the reason, said in the docs).
    """

    name: str
    group: str  # "clean" | "parameter" | "plain" | "concealed"
    truth: dict  # plant values of the truth (SI)
    kind: str = "step"
    amplitude: float = 0.3
    kp: float = 40.0
    ki: float = 0.0
    kd: float = 3.0
    v_limit: float = 6.0
    drop_v: bool = False
    expect: tuple = ()  # effects that should be named
    also: tuple = ()  # other sets of effects as right (rule "names")
    rule: str = "names"
    suggest: str = ""  # rule "not_explained": a phrase a suggestion must hold
    rate: float = 0.5  # open_ramp [V/s]
    horizon: float | None = None
    runs: tuple = ()
    seed: int = 1
    period: float = 1.0  # square [s]
    speed: float = 0.6  # tap, independent generator [m/s] (< 0: pushed towards -y)
    drop: tuple = ()
    generators: tuple = GENERATORS
    independent: dict = field(default_factory=dict)

    def __post_init__(self):
        if "," in self.name:  # --only takes a comma-separated list
            raise ValueError(f"case {self.name!r}: a name without commas")
        if self.rule not in RULES:
            raise ValueError(f"case {self.name!r}: rule {self.rule!r} is not one of {RULES}")
        unknown = set(self.independent) - set(INDEPENDENT_KEYS)
        if unknown or not set(self.generators) <= set(GENERATORS):
            raise ValueError(f"case {self.name!r}: independent {sorted(unknown)} or generators")

    def on(self, generator: str) -> Case:
        """The case as ``generator`` makes and judges it (``independent``'s changes applied)."""
        if generator == "exact" or not self.independent:
            return self
        ov = self.independent
        changes = {k: ov[k] for k in ("rule", "expect", "also", "suggest") if k in ov}
        return replace(self, truth={**self.truth, **ov.get("truth", {})}, **changes)

    def recordings(self) -> list[Case]:
        """The recordings of the case, each as a one-recording case."""
        if not self.runs:
            return [self]
        out = []
        for i, run in enumerate(self.runs):
            fields = {k: v for k, v in run.items() if k != "truth"}
            truth = {**self.truth, **run.get("truth", {})}
            out.append(replace(self, truth=truth, runs=(), seed=self.seed + i, **fields))
        return out


COULOMB, STICTION, SATURATION = Coulomb.name, Stiction.name, Saturation.name
DELAY, DEADZONE, SPRING, CURRENT = Delay.name, Deadzone.name, Spring.name, CurrentLimit.name
COULOMB_ASYM, VISCOUS_ASYM = CoulombAsymmetry.name, ViscousAsymmetry.name
DEADZONE_ASYM, OFFSET, TILT, STRIBECK = (
    DeadzoneAsymmetry.name,
    VoltageOffset.name,
    Tilt.name,
    Stribeck.name,
)
B = {"B_eq": 4.6}
#: Static friction on the independent generator: it falls to the kinetic level over a 2 mm/s
#: Stribeck speed (jaxcart's stiction drops at once). Coulomb + stiction names that truth
#: where the fall is not resolved, and Stribeck friction (f_s, f_c and v_stribeck, above its
#: least size of 1 mm/s) as rightly where it is: on the one cart hunting under PI it is fitted
#: at f_c 0.39995 N, f_s 0.909 N, v_stribeck 2.09 mm/s (truth 0.4, 0.9, 2).
STRIBECK_FALL = {"truth": {"v_stribeck": 0.002}, "also": ((COULOMB, STICTION, STRIBECK),)}
#: A lab cart as the real recordings show it (issue 21): viscous friction of a tap, 0.4 N of
#: Coulomb friction.
CART = {"B_eq": 1.5, "f_c": 0.4}
TAP = {"kind": "tap"}
P50 = {"kp": 50.0, "kd": 0.0, "amplitude": 0.15}
PD = {"kp": 50.0, "kd": 2.0, "amplitude": 0.2}
TRACK_RUN = {"kp": 40.0, "kd": 2.0}
#: A mild wave of friction along the track, 0.24-0.32 N (the levels at the knots, -0.4 to 0.4 m).
TRACK_WAVE = [0.2437, 0.3146, 0.3186, 0.3146, 0.2437]
PI_HUNT = {"kp": 30.0, "ki": 200.0, "kd": 1.0, "amplitude": 0.02, "horizon": 3.0}
PI_LAB = {"kp": 10.0, "ki": 15.0, "kd": 0.0, "amplitude": 0.1, "horizon": 3.0}


def _one_cart(what: str, truth: dict, runs: tuple, expect: tuple, **more) -> Case:
    """A concealed case of several runs of one cart, made by the independent generator."""
    return Case(what, "concealed", truth, runs=runs, expect=expect, generators=("independent",),
                **more)  # fmt: skip


#: Several recordings of one cart from the independent generator (issue 32): a tap and driven
#: runs, each run's drive drawn anew (gain 1 %, limits 3 %), the mechanics shared; a concealed
#: effect each. The last has an amplifier offset (a candidate since issue 33, a tie with a tilt
#: in closed loop): its runs disagree (a P 10 step up and down, an open-loop ramp), and are not
#: repeats of one experiment, so their disagreement excuses nothing.
ONE_CART = (
    _one_cart("one cart (tap + P 50 + PD): delay 8 ms", {**CART, "delay": 0.008},
              (TAP, P50, PD), (COULOMB, DELAY)),
    _one_cart("one cart (tap + P 50 + PD): current limit 1.2 A", {**CART, "i_max": 1.2},
              (TAP, P50, PD), (COULOMB, CURRENT)),
    _one_cart("one cart (tap + P 10 + PI hunting): stiction 0.9 N", {**CART, "f_s": 0.9},
              (TAP, {"kp": 10.0, "kd": 0.0, "amplitude": 0.1}, PI_HUNT), (COULOMB, STICTION),
              independent=STRIBECK_FALL),
    _one_cart("one cart (tap + P 50 + PD): cable spring 4 N/m", {**CART, "k_s": 4.0, "y_rest": 0.0},
              (TAP, P50, PD), (COULOMB, SPRING)),
    _one_cart("one cart (tap + P 50 + PI): deadzone 0.3 V", {**CART, "deadzone": 0.3},
              (TAP, P50, PI_LAB), (COULOMB, DEADZONE)),
    _one_cart("one cart (tap + two P 50): saturation per run and delay 12 ms",
              {**CART, "delay": 0.012},
              (TAP, {**P50, "amplitude": 0.2, "truth": {"v_sat": 5.1}},
               {**P50, "amplitude": 0.2, "truth": {"v_sat": 5.9}}),
              (COULOMB, DELAY, SATURATION), rule="per_run"),
    _one_cart("one cart (P 10 up and down + voltage ramp): drive offset 0.25 V",
              {**B, "v_offset": 0.25},
              ({"kp": 10.0, "kd": 0.0, "amplitude": 0.1},
               {"kp": 10.0, "kd": 0.0, "amplitude": -0.1},
               {"kind": "open_ramp", "rate": 0.5, "horizon": 2.0}),
              (OFFSET,)),
    # A shape no named effect has (issue 33): sliding friction rising with the speed to a
    # plateau, 0.3 N more moving right, 0.15 N left (TrueCart's rise); two taps each way.
    _one_cart("one cart (taps both ways): friction rising with speed",
              {**B, "f_c": 0.3, "rise_pos": 0.3, "rise_neg": 0.15, "v_rise": 0.03},
              tuple({**TAP, "speed": v} for v in (0.6, -0.6, 0.4, -0.4)), (), rule="curve"),
    # Friction rising along the track, 0.4 N more from +0.2 m on than before -0.2 m (the truth
    # a table, linear between its points; jaxcart's curve a smooth map through levels at knots
    # 0.2 m apart, which holds it within 0.018 N over +-0.3 m at best, 0.022 N through its
    # levels at the knots): steps and out-and-back runs that cover +-0.3 m, both ways.
    _one_cart("one cart (steps and out-and-back both ways): friction along the track",
              {**B, "f_c": 0.2, "track_y": (-0.4, -0.2, 0.2, 0.4), "track_f": (0, 0, 0.4, 0.4)},
              tuple({**TRACK_RUN, "kind": kind, "amplitude": a}
                    for kind in ("step", "out_back") for a in (0.3, -0.3)),
              (), rule="curve"),
)  # fmt: skip
CASES = (
    Case("clean PD step", "clean", B, rule="nothing"),
    Case("clean PID step", "clean", B, ki=5.0, rule="nothing"),
    Case("clean ramp reference", "clean", B, kind="ramp", amplitude=0.2, rule="nothing"),
    Case("clean tap", "clean", {"B_eq": 1.5}, kind="tap", rule="nothing"),
    Case(
        "clean tap + PD step (one cart)",
        "clean",
        {"B_eq": 1.5},
        kp=50.0,
        kd=2.0,
        amplitude=0.1,
        runs=({"kind": "tap"}, {}),
        rule="nothing",
    ),
    Case("heavier cart (M)", "parameter", {**B, "M": 1.25}, rule="corrected"),
    Case("weaker motor (gamma)", "parameter", {**B, "gamma_scale": 0.8}, rule="corrected"),
    Case("saturation plain", "plain", {**B, "v_sat": 4.0}, amplitude=0.4, expect=(SATURATION,)),
    Case(
        "saturation brief (first 0.1 s)",
        "concealed",
        {**B, "v_sat": 5.0},
        amplitude=0.2,
        kp=30.0,
        expect=(SATURATION,),
    ),
    Case("coulomb plain", "plain", {**B, "f_c": 0.4}, expect=(COULOMB,)),
    Case(
        "coulomb under PI (error goes to 0)",
        "concealed",
        {**B, "f_c": 0.3},
        ki=20.0,
        expect=(COULOMB,),
        rule="exact",
    ),
    Case(
        "coulomb under PI on a lab cart (no deadzone)",
        "concealed",
        CART,
        amplitude=0.1,
        kp=30.0,
        ki=30.0,
        kd=1.5,
        expect=(COULOMB,),
        rule="exact",
    ),
    Case("coulomb without v", "concealed", {**B, "f_c": 0.4}, drop_v=True, expect=(COULOMB,)),
    Case("coulomb on a tap", "plain", {"B_eq": 1.5, "f_c": 0.44}, kind="tap", expect=(COULOMB,)),
    # Static friction that leaves no trace: the step's first command already pushes with more
    # than f_s (0.78 N against 0.6 N; 0.69 N against 0.5 N), and the cart sticks once, at
    # 1.4 s (1.2 s), never to break away again within the recording. Coulomb friction alone
    # fits it to the encoder floor; stiction named here would not have earned its place.
    Case(
        "stiction unseen (small step)",
        "plain",
        {**B, "f_c": 0.3, "f_s": 0.6},
        amplitude=0.03,
        kp=15.0,
        ki=30.0,
        kd=1.0,
        expect=(COULOMB,),
    ),
    Case(
        "stiction unseen under PI",
        "concealed",
        {**B, "f_c": 0.3, "f_s": 0.5},
        amplitude=0.02,
        kp=20.0,
        ki=40.0,
        kd=1.0,
        expect=(COULOMB,),
    ),
    # Static friction 1.5 times kinetic, where Coulomb friction alone cannot fit: a 0.1 V/s
    # ramp breaks the cart away at 0.35 V (3.5 s; Coulomb alone would move it from 0.23 V)
    # and it jumps to 16 mm/s within 0.1 s; a PI loop hunts about its target by stick-slip, four
    # stops within 3 s, 7 to 3 mm either side of it.
    Case(
        "stiction breakaway on a 0.1 V/s ramp",
        "plain",
        {**B, "f_c": 0.4, "f_s": 0.6},
        kind="open_ramp",
        rate=0.1,
        horizon=5.0,
        expect=(COULOMB, STICTION),
    ),
    Case(
        "stiction hunting under PI",
        "concealed",
        {**B, "f_c": 0.4, "f_s": 0.6},
        amplitude=0.01,
        kp=40.0,
        ki=400.0,
        kd=1.5,
        horizon=3.0,
        expect=(COULOMB, STICTION),
    ),
    Case("delay plain", "plain", {**B, "delay": 0.004}, kp=60.0, kd=4.0, expect=(DELAY,)),
    Case(
        "delay without v",
        "concealed",
        {**B, "delay": 0.002},
        kp=60.0,
        kd=4.0,
        drop_v=True,
        expect=(DELAY,),
    ),
    Case(
        "delay with coulomb",
        "concealed",
        {**B, "delay": 0.003, "f_c": 0.3},
        kp=60.0,
        kd=4.0,
        expect=(COULOMB, DELAY),
    ),
    Case("deadzone plain", "plain", {**B, "deadzone": 0.4}, expect=(DEADZONE,)),
    Case(
        "deadzone without v", "concealed", {**B, "deadzone": 0.3}, drop_v=True, expect=(DEADZONE,)
    ),
    Case(
        "deadzone on an open-loop ramp (= coulomb)",
        "concealed",
        {**B, "deadzone": 0.5},
        kind="open_ramp",
        horizon=3.0,
        expect=(DEADZONE,),
    ),
    Case("spring plain", "plain", {**B, "k_s": 6.0, "y_rest": 0.0}, expect=(SPRING,)),
    Case(
        "spring under PID",
        "concealed",
        {**B, "k_s": 3.0, "y_rest": 0.0},
        ki=10.0,
        expect=(SPRING,),
    ),
    Case(
        "current limit plain",
        "plain",
        {**B, "i_max": 1.5},
        amplitude=0.4,
        expect=(CURRENT,),
    ),
    Case(
        "current limit with coulomb",
        "concealed",
        {**B, "i_max": 2.0, "f_c": 0.3},
        amplitude=0.4,
        expect=(COULOMB, CURRENT),
    ),
    Case(
        "current limit with coulomb on a lab cart (PD)",
        "concealed",
        {**CART, "i_max": 1.2},
        amplitude=0.15,
        kp=50.0,
        kd=2.0,
        expect=(COULOMB, CURRENT),
    ),
    Case(
        "saturation with coulomb",
        "concealed",
        {**B, "v_sat": 4.5, "f_c": 0.3},
        amplitude=0.3,
        expect=(COULOMB, SATURATION),
    ),
    # One cart, several runs (issue 21): mechanics shared, the amplifier's limit differs from
    # run to run (the motor warms, the supply sags); the tap has the motor unplugged.
    Case(
        "tap + P and PD steps with the drive limit per run",
        "concealed",
        CART,
        amplitude=0.15,
        kp=50.0,
        kd=0.0,
        runs=(TAP, {"truth": {"v_sat": 4.6}}, {"kd": 2.0, "truth": {"v_sat": 5.5}}),
        expect=(COULOMB, SATURATION),
        rule="per_run",
    ),
    Case(
        "tap + two P steps with one drive limit",
        "concealed",
        {**CART, "v_sat": 5.0},
        amplitude=0.15,
        kp=50.0,
        kd=0.0,
        runs=(TAP, {}, {"amplitude": 0.12}),
        expect=(COULOMB, SATURATION),
        rule="shared",
        independent={
            "artefacts": {"limit_spread": 0.0, "gain_spread": 0.0},
            "why": "one drive: on the independent generator neither the limit nor the gain "
            "varies from run to run here (with the gain drawn anew each run, the gain per run "
            "is named, rightly)",
        },
    ),
    # Physics beyond the first library (issue 33): friction, a dead band that differ by
    # direction (a reference out and back), offsets, the Stribeck fall.
    Case(
        "coulomb by direction",
        "plain",
        {**B, "f_c": 0.3, "f_c_asym": 0.1},
        kind="out_back",
        expect=(COULOMB, COULOMB_ASYM),
    ),
    Case(
        "viscous by direction",
        "plain",
        {**B, "B_asym": 1.2},
        kind="out_back",
        expect=(VISCOUS_ASYM,),
    ),
    Case(
        "deadzone by direction",
        "plain",
        {**B, "deadzone": 0.4, "deadzone_asym": 0.15},
        kind="out_back",
        expect=(DEADZONE, DEADZONE_ASYM),
    ),
    # In closed loop a voltage offset is a tilt (gamma v_offset = f_tilt): named as a tie.
    Case("voltage offset", "plain", {**B, "v_offset": 0.25}, expect=(OFFSET,)),
    # The tap (motor unplugged) tells the tilt from an offset of the drive.
    Case(
        "tilt (tap + PD step)",
        "concealed",
        {"B_eq": 1.5, "f_tilt": 0.3},
        amplitude=0.15,
        kp=50.0,
        kd=2.0,
        runs=(TAP, {}),
        expect=(TILT,),
    ),
    Case(
        "stribeck hunting under PI",
        "concealed",
        {**B, "f_c": 0.4, "f_s": 0.6, "v_stribeck": 0.01},
        amplitude=0.01,
        kp=40.0,
        ki=400.0,
        kd=1.5,
        horizon=3.0,
        expect=(COULOMB, STICTION, STRIBECK),
    ),
    Case(
        "track friction (no candidate)",
        "concealed",
        {**B, "f_track": TRACK_WAVE},
        amplitude=0.4,
        rule="not_explained",
        suggest="along the track",
        independent={
            "truth": {"f_track": [0.05, 0.6, 0.05, 0.6, 0.05]},
            "why": "the independent generator's friction is a table through 0.05-0.6 N, "
            "linear between its points; jaxcart's map through those levels would swing 0.65 N "
            "between the knots, where the case's mild wave is 0.24-0.32 N",
        },
    ),
    Case(
        "coulomb under PI recorded as its error (no y)",
        "concealed",
        {**B, "f_c": 0.3},
        ki=20.0,
        drop=("y",),
        expect=(COULOMB,),
        rule="exact",
    ),
    # Strong static friction (issue 32): 2.5 and 2.2 times kinetic at 2.0 and 2.2 N. The ramp
    # holds the cart until 3.87 s (f_s / (gamma 0.3 V/s)), then it lurches; the PI loop hunts
    # about its target by stick-slip, five stops within 3 s, up to 13 mm either side. On the
    # independent generator friction falls from the breakaway level to the kinetic one over a
    # 2 mm/s Stribeck speed (:data:`STRIBECK_FALL`).
    Case(
        "strong stiction breakaway on a 0.3 V/s ramp (a late lurch)",
        "plain",
        {**B, "f_c": 0.8, "f_s": 2.0},
        kind="open_ramp",
        rate=0.3,
        horizon=5.0,
        expect=(COULOMB, STICTION),
        independent=STRIBECK_FALL,
    ),
    Case(
        "strong stiction hunting under PI",
        "concealed",
        {**B, "f_c": 1.0, "f_s": 2.2},
        amplitude=0.01,
        kp=40.0,
        ki=400.0,
        kd=1.5,
        horizon=3.0,
        expect=(COULOMB, STICTION),
        independent=STRIBECK_FALL,
    ),
    *ONE_CART,
)
FAST = (
    "clean PD step",
    "heavier cart (M)",
    "coulomb plain",
    "saturation brief (first 0.1 s)",
    "track friction (no candidate)",
)


def make_case(case: Case, folder, generator: str = "exact") -> list[Path]:
    """Make each recording of ``case`` with ``generator`` (:data:`GENERATORS`) and write each
    as an experiment file in ``folder``; their paths."""
    return [path for path, _ in make_recordings(case, folder, generator)]


def make_recordings(case: Case, folder, generator: str = "exact") -> list[tuple[Path, dict]]:
    """:func:`make_case`'s paths, each with the truth its run had ({name: value}, SI: on the
    independent generator a driven run's drive is drawn anew from run to run)."""
    if generator not in case.generators:
        raise ValueError(f"case {case.name!r} is not made by the {generator} generator")
    case = case.on(generator)
    slug = "".join(ch if ch.isalnum() else "_" for ch in case.name).strip("_")
    runs = case.recordings()
    if generator == "exact":
        write = _write_run
    else:
        write = partial(_write_independent, several=len(runs) > 1)
    if len(runs) == 1:
        return [write(runs[0], Path(folder) / f"{slug}.toml")]
    return [write(run, Path(folder) / f"{slug}_{i}.toml") for i, run in enumerate(runs)]


def _write_run(case: Case, path: Path) -> tuple[Path, dict]:
    truth, horizon = case.truth, case.horizon
    if case.kind == "tap":
        plant = build_plant(truth, motor_connected=False)
        rec = make_tap_recording(plant, speed=0.6, rest=0.3, horizon=horizon or 1.5, seed=case.seed)
    else:
        plant = build_plant(truth)
        pid = jc.PID(kp=case.kp, ki=case.ki, kd=case.kd, v_limit=case.v_limit)
        if case.kind == "step":
            exp = jc.step(case.amplitude, horizon=horizon or 2.0)
        elif case.kind == "out_back":
            h = horizon or 2.0
            exp = jc.setpoints([0.0, h / 2], [case.amplitude, -case.amplitude / 2], horizon=h)
        elif case.kind == "ramp":
            exp = jc.ramp(case.amplitude, horizon=horizon or 2.0)
        elif case.kind == "square":
            horizon = horizon or 2.0
            times = [i * case.period / 2 for i in range(int(2 * horizon / case.period) + 1)]
            values = [case.amplitude if i % 2 == 0 else 0.0 for i in range(len(times))]
            exp = jc.setpoints(times, values, horizon=horizon)
        elif case.kind == "open_ramp":
            exp = jc.voltage_ramp(case.rate, horizon=horizon or 3.0)
            pid = None
        else:
            raise ValueError(f"case {case.name!r}: kind {case.kind!r}: give {', '.join(KINDS)}")
        rec = make_recording(plant, pid, exp, seed=case.seed)
    write_recording(rec, path, force=True)
    if rec.kind == "tap":
        text = path.read_text()
        if "[tap]" not in text:
            path.write_text(text + "\n[tap]\nmotor_connected = false\n")
    for column in ("v",) * case.drop_v + tuple(case.drop):
        _drop_column(path.with_suffix(".csv"), column)
    return path, dict(truth)


def _write_independent(case: Case, path: Path, several: bool) -> tuple[Path, dict]:
    """A recording of ``case`` by :mod:`tuning.verification`, with REALISTIC artefacts (and
    the case's changes to them); ``several``: one of several runs of one cart."""
    horizon = case.horizon
    pid = jc.PID(kp=case.kp, ki=case.ki, kd=case.kd, v_limit=case.v_limit)
    made = {
        "tap": lambda: ex.tap(speed=case.speed, rest=0.3, horizon=horizon or 1.5),
        "step": lambda: ex.step(pid, case.amplitude, horizon=horizon or 2.0),
        "ramp": lambda: ex.ramp(pid, case.amplitude, horizon=horizon or 2.0),
        "square": lambda: ex.square(
            pid, case.amplitude, period=case.period, horizon=horizon or 2.0
        ),
        "out_back": lambda: ex.square(
            pid,
            case.amplitude,
            period=horizon or 2.0,
            horizon=horizon or 2.0,
            low=-case.amplitude / 2,
        ),  # fmt: skip
        "open_ramp": lambda: ex.voltage_ramp(case.rate, horizon=horizon or 3.0),
    }
    if case.kind not in made:
        raise ValueError(f"case {case.name!r}: kind {case.kind!r}: give {', '.join(KINDS)}")
    # The drive's spread is from run to run: a case of one recording has the cart's own drive.
    spread = {} if several else {"gain_spread": 0.0, "limit_spread": 0.0}
    artefacts = REALISTIC.replace(**{**spread, **case.independent.get("artefacts", {})})
    drop = ("v",) * case.drop_v + tuple(case.drop)
    rec = make_independent_recording(
        TrueCart.from_values(case.truth),
        made[case.kind](),
        path,
        artefacts,
        seed=case.seed,
        force=True,
        drop=drop,
    )
    return rec.path, rec.run.truth.values()


def _drop_column(csv_path: Path, column: str) -> None:
    with csv_path.open() as f:
        rows = list(csv.reader(f))
    header = rows[0]
    if column not in header:
        return
    k = header.index(column)
    with csv_path.open("w", newline="") as f:
        w = csv.writer(f)
        for row in rows:
            w.writerow(row[:k] + row[k + 1 :])


def judge(case: Case, d, truths: list[dict] | None = None) -> dict:
    """The score row of diagnosis ``d`` of ``case`` (as its generator made it,
    :meth:`Case.on`): what was expected and named, whether that is right by the case's rule
    (:data:`RULES`), and whether it is a false alarm (an effect or a correction named on a
    clean case, the drive freed per run where the runs share it: where their truths give them
    one limit). ``truths``: each recording's own truth (:func:`make_recordings`; default: the
    case's)."""
    named = set(d.left_out)
    expect = set(case.expect)
    chosen = next((c for c in d.candidates if c.name == d.chosen), None)
    per_run = chosen is not None and PER_RUN in chosen.parts
    right = {
        "names": lambda: (
            named in [expect, *map(set, case.also)] or expect in [set(e) for e in d.equivalent]
        ),
        "exact": lambda: named == expect,
        "nothing": lambda: not named and not d.corrected_parameters,
        "corrected": lambda: not named and bool(d.corrected_parameters),
        "per_run": lambda: named == expect and per_run and _own_limits_right(case, d, truths),
        "shared": lambda: named == expect and not per_run,
        "not_explained": lambda: not d.explained and any(case.suggest in s for s in d.suggestions),
        "curve": lambda: _curve_right(d, truths or [case.truth]),
    }[case.rule]
    varies = case.rule == "per_run" or _limits_vary(truths)
    curve, had = _curve_named(d), truths or [case.truth]
    false_alarm = (
        (case.group in ("clean", "parameter") and (bool(named) or bool(curve)))
        or (per_run and not varies)
        or (curve == "speed" and not _speed_friction(had))
        or (curve == "track" and not _track_friction(had))
    )
    return {
        "case": case.name,
        "group": case.group,
        "rule": case.rule,
        "expected": _expected_text(case),
        "named": sorted(named) + [PER_RUN] * per_run + [f"{curve} curve"] * bool(curve),
        "corrected": d.corrected_parameters,
        "equivalent": d.equivalent,
        "explained": d.explained,
        "correct": bool(d.status == "diagnosed" and right()),
        "false_alarm": false_alarm,
        "rms_before": d.rms_before,
        "rms_after": d.rms_after,
        "ratio": d.rms_before / d.rms_after if d.rms_after > 0 else math.inf,
        "seconds": d.seconds,
    }


def _curve_named(d) -> str | None:
    """The curve a diagnosis named: "speed", "track" or None."""
    fc = d.friction_curve
    if fc.get("named"):
        return "speed"
    return "track" if fc.get("track", {}).get("named") else None


def _curve_right(d, truths) -> bool:
    """The curve of the truth's shape named (along the track where the truth's friction
    varies there, else of the speed), and within CURVE_TOLERANCE of the truth's friction
    where the recordings determine it (the first recording's truth: the mechanics are one
    cart's)."""
    truth = TrueCart.from_values(dict(truths[0]))
    if _track_friction(truths):
        return _curve_named(d) == "track" and _track_right(d.friction_curve["track"], truth)
    if _curve_named(d) != "speed":
        return False
    c = d.friction_curve["curve"]
    for side, direction in (("right", 1), ("left", -1)):
        for q, level, band in zip(c["speeds"], c["levels"].get(side, ()), c["bands"].get(side, ()),
                                  strict=False):  # fmt: skip
            want = truth.kinetic(direction) + truth.rise(direction, q)
            if q >= 0.08 and band is not None and abs(level - want) > CURVE_TOLERANCE:
                return False
    return True


def _track_right(shape: dict, truth) -> bool:
    """The curve along the track read where it was fitted (its levels at two knots or more)
    within CURVE_TOLERANCE of the truth's kinetic friction there (between them the map is an
    interpolation, also through the levels it held)."""
    c = shape["curve"]
    return len(c["positions"]) >= 2 and all(
        abs(level - truth.kinetic(1, q)) <= CURVE_TOLERANCE
        for q, level in zip(c["positions"], c["levels"], strict=True)
    )


def _track_friction(truths) -> bool:
    """Whether a truth's friction varies along the track."""
    return any(len(set(t.get("track_f", ()))) > 1 or len(set(t.get("f_track", ()))) > 1
               for t in truths)  # fmt: skip


def _speed_friction(truths) -> bool:
    """Whether a truth's friction varies with the speed (a rise, a Stribeck fall, viscous
    friction by direction): a curve named there reads physics that is there."""
    keys = ("rise_pos", "rise_neg", "v_stribeck", "B_asym", "B_pos", "B_neg")
    return any(t.get(k) for t in truths for k in keys)


def _expected_text(case: Case) -> list:
    if case.rule == "corrected":
        return ["corrected M/gamma"]
    if case.rule == "curve":
        return ["friction curve" + (" along the track" if _track_friction([case.truth]) else "")]
    if case.rule == "not_explained":
        return [f"not explained ({case.suggest})"]
    extra = {"per_run": ["per_run"], "exact": ["only"]}.get(case.rule, [])
    also = [f"or {'+'.join(sorted(a))}" for a in case.also]
    return sorted(case.expect) + extra + also


def _limits_vary(truths) -> bool:
    """Whether the runs' drives (limits, gain) differ in their truths (the independent
    generator draws each run's anew): freeing them per run is then no false alarm."""
    for name in per_run_params():
        values = {t[name] for t in truths or () if name in t and t.get("motor_connected", True)}
        if len(values) > 1:
            return True
    return False


def _own_limits_right(case: Case, d, truths=None) -> bool:
    """Each driven run's own drive limit (Diagnosis.per_recording) within PER_RUN_TOLERANCE of
    its truth, and no own limit for a tap (the motor unplugged)."""
    runs = case.recordings()
    truths = truths or [run.truth for run in runs]
    recorded = list(d.per_recording.values())
    if len(recorded) != len(runs):
        return False
    for run, truth, rec in zip(runs, truths, recorded, strict=True):
        own = rec.get("parameters", {})
        if run.kind == "tap":
            if own:
                return False
            continue
        limits = [n for n in own if n in truth]
        if not limits:
            return False
        for n in limits:
            if abs(own[n]["value"] - truth[n]) > PER_RUN_TOLERANCE * truth[n]:
                return False
    return True


def run_suite(
    names=None, progress=False, out=sys.stdout, generators=GENERATORS, executor=None, curve=False
) -> list[dict]:
    """Diagnose every chosen case made by each of ``generators`` (``curve``: with friction read
    as a curve where nothing named explains, ``diagnose(curve=True)``; a case of
    rule "curve" is left out without it); the score rows (each with its ``generator``),
    printed as they come."""
    chosen = [c for c in CASES if (names is None or c.name in names)]
    chosen = [c for c in chosen if curve or c.rule != "curve"]
    unknown = sorted(set(names or ()) - {c.name for c in CASES})
    if unknown:
        raise SystemExit(f"suite: no case named {', '.join(map(repr, unknown))}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for generator in generators:
            folder = Path(tmp) / generator
            folder.mkdir()
            for case in (c for c in chosen if generator in c.generators):
                made = make_recordings(case, folder, generator)
                t = time.perf_counter()
                d = diagnose(
                    [read_experiment(p) for p, _ in made],
                    progress=progress,
                    executor=executor,
                    curve=curve,
                )
                row = judge(case.on(generator), d, [truth for _, truth in made])
                row["seconds"] = round(time.perf_counter() - t, 2)
                row["generator"] = generator
                row["verdict"] = d.verdict
                rows.append(row)
                print(_row_text(row), file=out, flush=True)
    return rows


def _row_text(r) -> str:
    named = ", ".join(r["named"]) or (
        "corrected " + ", ".join(r["corrected"]) if r["corrected"] else "-"
    )
    if r["equivalent"]:
        named += " (or " + "; ".join("+".join(e) for e in r["equivalent"]) + ")"
    if not r["explained"]:
        named += " [not explained]"
    expected = ", ".join(r["expected"]) or "-"
    return (
        f"{'ok  ' if r['correct'] else 'MISS'}{' ALARM' if r['false_alarm'] else ''} "
        f"{r.get('generator', 'exact')[:5]:<5} {r['case']:<46} expected: {expected:<34} "
        f"named: {named:<44} "
        f"RMS {r['rms_before'] * 1e3:8.4f} -> {r['rms_after'] * 1e3:7.4f} mm "
        f"({r['ratio']:7.1f}x) {r['seconds']:5.1f} s"
    )


def summary(rows) -> str:
    n = len(rows)
    correct = sum(r["correct"] for r in rows)
    guard = [r for r in rows if r["group"] in ("clean", "parameter")]
    shared = [r for r in rows if r["rule"] == "shared"]
    ratios = [r["ratio"] for r in rows]
    effect_ratios = [r["ratio"] for r in rows if r["group"] in ("plain", "concealed", "parameter")]
    secs = [r["seconds"] for r in rows]
    return (
        f"correct: {correct}/{n}; false alarms: {sum(r['false_alarm'] for r in guard)}/"
        f"{len(guard)} clean and parameter-error cases naming an effect, "
        f"{sum(r['false_alarm'] for r in shared)}/{len(shared)} runs sharing their drive "
        f"given one limit per run; median RMS ratio before/after: "
        f"{statistics.median(ratios):.1f}x (all), "
        f"{statistics.median(effect_ratios) if effect_ratios else float('nan'):.1f}x "
        f"(cases with an effect or parameter error); seconds per case: median "
        f"{statistics.median(secs):.1f}, max {max(secs):.1f}, total {sum(secs):.0f}"
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m tuning.estimation.diagnose.suite")
    p.add_argument("--fast", action="store_true", help="the CI subset")
    p.add_argument("--only", help="comma-separated case names")
    p.add_argument(
        "--generator",
        choices=(*GENERATORS, "both"),
        default="both",
        help="who makes the recordings: jaxcart's exact simulator, the independent generator "
        "(tuning.verification) or both (default)",
    )
    p.add_argument("--json", dest="json_out", help="write the score rows to this JSON file")
    p.add_argument("--progress", action="store_true")
    p.add_argument(
        "--curve",
        action="store_true",
        help="diagnose with friction read as a curve of the speed and of the position where "
        "nothing named explains (and score the cases whose friction only a curve has)",
    )
    args = p.parse_args(argv)
    names = FAST if args.fast else (args.only.split(",") if args.only else None)
    generators = GENERATORS if args.generator == "both" else (args.generator,)
    with Helpers() as helpers:  # the exact runs several at a time, closed at the end
        rows = run_suite(
            names,
            progress=args.progress,
            generators=generators,
            executor=helpers,
            curve=args.curve,
        )
    for generator in generators:
        mine = [r for r in rows if r["generator"] == generator]
        if mine:
            print(f"{generator}: {summary(mine)}")
    if args.json_out:
        write_json(args.json_out, rows)
    return 0


if __name__ == "__main__":
    enable_persistent_cache()  # as the command line does: compiled batches kept on disk
    use_cpu_devices()
    sys.exit(main())
