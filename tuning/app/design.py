"""The numbers behind the design page, with no drawing: one slider position in, the exact step
response, its metrics against the handout's specification, the closed-loop poles and the feasible
region of the (kp, kd) plane out.

    sliders (kp, ki, kd, tau, setpoint) --> Settings --> DesignProblem.design --> Design
                                                     |    exact run (solver=Exact()), StepInfo,
                                                     |    checks against the spec, poles
                                                     '--> DesignProblem.region --> Region
                                                          batched grid (jaxcart.batch_metrics) at ki

The specification is the tuner's (:class:`tuning.design.losses.Spec`: 0.5 m step, 2 % settling
under 1 s, overshoot under 5 %, 3 s horizon) with the lab amplifier's 6 V as the controller's
software limit (:data:`jaxcart.plausibility.LAB_VOLTAGE`). Units: gains kp [V/m], ki [V/(m s)],
kd [V s/m]; tau [s]; positions [m]; times [s]; voltages [V]; poles [1/s].

>>> problem = DesignProblem()
>>> design = problem.design(Settings(kp=40.0, ki=5.0, kd=5.0))
>>> round(design.info.overshoot, 1) < 5.0, design.stable
(True, True)
"""

from __future__ import annotations

import dataclasses
import functools
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

import jaxcart as jc
from hw.control_law import PID, setting_problem
from jaxcart import control_systems
from jaxcart.batch_metrics import step_metrics_batch
from jaxcart.errors import UserError
from jaxcart.files import read_experiment
from jaxcart.params import TRAVEL
from jaxcart.plantspec import FORMAT, read_plant_file
from jaxcart.plausibility import LAB_VOLTAGE
from tuning.design.grid_blocks import feasible_mask
from tuning.design.losses import Spec
from tuning.design.margins import Margins, margins
from tuning.design.problem import HANDOUT_START

#: The page's simulator: the exact one (event-exact friction, hard clip at the 6 V limit).
EXACT = jc.Exact()
#: The lab's design problem (the tuner's).
SPEC = Spec()
#: The software voltage limit of the lab's controller [V] (the amplifier's range).
V_LIMIT = LAB_VOLTAGE
#: The sliders in the handout's order (kp, ki, kd), then the derivative filter tau [s] and the
#: setpoint [m]: (low, high, step). kp to 250 V/m and ki to 30 V/(m s) as the tuner's and the
#: grid's boxes; the setpoint within the cart's travel (0.814 m), so that a recorded step of
#: any size the track allows can be matched.
RANGES = {
    "kp": (0.0, 250.0, 1.0),
    "ki": (0.0, 30.0, 0.1),
    "kd": (0.0, 20.0, 0.1),
    "tau": (0.0, 0.05, 0.0005),
    "setpoint": (-0.8, 0.8, 0.01),
}
UNITS = {"kp": "V/m", "ki": "V/(m s)", "kd": "V s/m", "tau": "s", "setpoint": "m"}


def snap(name: str, value: float) -> float:
    """``value`` [SI] of the slider ``name`` as the slider can hold it: within its range, on its
    step (a click on the region lands between steps; the page shows the slider's value)."""
    lo, hi, step = RANGES[name]
    on_step = lo + round((float(value) - lo) / step) * step
    # Rounded to the step's decimals: 0.1 * 75 is 7.500000000000001.
    decimals = max(0, -math.floor(math.log10(step))) + 1
    return round(min(max(on_step, lo), hi), decimals)


#: Points per axis of the feasible region: 32 x 32 runs of 3 s take about 10 ms (float32,
#: 2 cores, measured), well inside the page's 100 ms for a slider move.
REGION_POINTS = 32
#: Region status codes, in the order of :data:`STATUS_NAMES`.
FEASIBLE, OVERSHOOTS, SLOW, BOTH, DIVERGED = range(5)
STATUS_NAMES = ("meets the spec", "overshoot too high", "settles too slowly", "both", "diverges")


@dataclass(frozen=True)
class Settings:
    """One position of the sliders: kp [V/m], ki [V/(m s)], kd [V s/m], tau [s] (derivative
    filter time constant, Simulink N = 1/tau; 0 is a pure difference), setpoint [m] (the step's
    target from rest at 0 m)."""

    kp: float = HANDOUT_START[0]
    ki: float = HANDOUT_START[2]
    kd: float = HANDOUT_START[1]
    tau: float = 0.01
    setpoint: float = SPEC.step

    def __post_init__(self):
        for name in RANGES:
            value = getattr(self, name)
            if name != "setpoint":  # the one rule of a PID setting (gains >= 0, tau >= 0)
                problem = setting_problem(name, value)
                if problem:
                    raise UserError(f"{name} = {problem}")
            elif not (isinstance(value, float | int) and math.isfinite(value)):
                raise UserError(f"{name} = {value!r} {UNITS[name]}: give a finite number")

    def controller(self) -> PID:
        """The lab's PID with these gains and the 6 V software limit."""
        return PID(kp=self.kp, ki=self.ki, kd=self.kd, tau=self.tau, v_limit=V_LIMIT)


@dataclass(frozen=True)
class Check:
    """One metric against the specification: name, value (unit ``unit``; inf: never reached),
    bound (None: shown, not bounded), ok (None without a bound)."""

    name: str
    value: float
    unit: str
    bound: float | None = None

    @property
    def ok(self) -> bool | None:
        return None if self.bound is None else bool(self.value < self.bound)


@dataclass(frozen=True, eq=False)
class Design:
    """What one slider position shows. response: the exact run on the design plant (a
    :class:`jaxcart.Response`); info: its :class:`StepInfo` (None at setpoint 0, no step);
    checks: the metrics against the spec; meets: the spec is met; poles: closed-loop poles of
    the linear digital loop as s = ln(z)/Ts [1/s] (no 6 V limit, no friction); stable: every
    |z| < 1; nominal: the same gains on the handout's plant when the design plant is a fitted
    one (else None); margins: the gain and phase margins, the peak sensitivity and the
    encoder's ripple of the gains on the design plant, its delay included
    (:func:`tuning.design.margins.margins`)."""

    settings: Settings
    response: object
    info: jc.StepInfo | None
    checks: tuple[Check, ...]
    meets: bool
    poles: np.ndarray
    stable: bool
    nominal: object = None
    excursion: float = 0.0
    margins: Margins | None = None

    @property
    def on_track(self) -> bool:
        return self.excursion < TRAVEL


@dataclass(frozen=True, eq=False)
class Region:
    """The feasible region of the (kp, kd) plane at one ki, tau and setpoint: kp [V/m] and kd
    [V s/m] axes; status[i_kd, i_kp] one of the status codes; settling_time [s] and overshoot
    [%] of each point (hard-clip digital loop, float32: a point on the boundary may read the
    other way than the exact run)."""

    kp: np.ndarray
    kd: np.ndarray
    ki: float
    tau: float
    setpoint: float
    status: np.ndarray
    settling_time: np.ndarray
    overshoot: np.ndarray

    @property
    def n_feasible(self) -> int:
        return int(np.count_nonzero(self.status == FEASIBLE))


@dataclass(frozen=True, eq=False)
class Overlay:
    """A student's closed-loop step recording, as the page draws it: time from its first
    sample [s], position and reference relative to the start y0 [m], the command [V] (None
    without one), its step metrics (None unless the reference is a step), the gains it ran
    (None without a [controller]) and its file name."""

    name: str
    time: np.ndarray
    position: np.ndarray
    reference: np.ndarray
    command: np.ndarray | None
    info: jc.StepInfo | None
    controller: PID | None
    y0: float


#: The metric table's row of the track's travel (its bound :data:`TRAVEL`).
EXCURSION = "largest |y - y0|"


def checks_of(
    info: jc.StepInfo, spec: Spec = SPEC, excursion: float | None = None
) -> tuple[Check, ...]:
    """The page's metric table: rise time, settling time (< spec), overshoot (< spec), the
    error at the end of the run (step_info's steady_state_error is |r - y| at the last sample:
    with an integrator still closing it, no steady state), peak voltage, the time spent at the
    6 V limit and, given ``excursion`` [m], the largest |y - y0| against the track's travel."""
    checks = (
        Check("rise time", info.rise_time, "s"),
        Check("settling time", info.settling_time, "s", spec.settling_time),
        Check("overshoot", info.overshoot, "%", spec.overshoot),
        Check(f"error at t = {spec.horizon:g} s", info.steady_state_error, "m"),
        Check("peak voltage", info.peak_voltage, "V"),
        Check(f"time at {V_LIMIT:g} V", info.saturation_time, "s"),
    )
    if excursion is None:
        return checks
    return (*checks, Check(EXCURSION, excursion, "m", TRAVEL))


def s_plane(z: np.ndarray, sample_time: float) -> np.ndarray:
    """Discrete poles z as their s-plane equivalents s = ln(z)/Ts [1/s]; a pole at z = 0 (a
    pure-difference derivative) becomes a very fast real pole instead of -inf."""
    z = np.asarray(z, dtype=complex)
    tiny = 1e-12
    z = np.where(np.abs(z) < tiny, tiny, z)
    return np.log(z) / sample_time


def loop_poles(plant, pid, plant_ss=None) -> np.ndarray:
    """Poles z of the digital loop of ``plant`` under ``pid``: with ``plant_ss``
    (:func:`jaxcart.control_systems.plant_ss` of the plant at the PID's sample time, kept by the
    caller) and :func:`jaxcart.control_systems.controller_ss`,
    the eigenvalues of the feedback's state matrix, the poles
    :func:`jaxcart.control_systems.closed_loop_poles` finds by interconnecting the two, without
    its ~10 ms of bookkeeping per call (the page asks at every slider move).

        plant   x+ = Ap x + Bp u,  y = Cp x  (a sampled cart has no feedthrough)
        PID     w+ = Ac w + Bc (r, y),  u = Cc w + Dc (r, y)
        loop    [x; w]+ = [[Ap + Bp Dy Cp, Bp Cc], [By Cp, Ac]] [x; w] + (r terms)
    """
    if plant_ss is None:
        plant_ss = control_systems.plant_ss(plant, pid.sample_time)
    if np.any(plant_ss.D != 0):  # not a sampled cart: python-control interconnects it
        return control_systems.closed_loop_poles(plant, pid)
    c = control_systems.controller_ss(pid)
    ap, bp, cp = plant_ss.A, plant_ss.B, plant_ss.C
    by, dy = c.B[:, 1:2], c.D[:, 1:2]
    a = np.block([[ap + bp @ dy @ cp, bp @ c.C], [by @ cp, c.A]])
    return np.linalg.eigvals(a)


def region_status(info: jc.StepInfo, spec: Spec = SPEC) -> np.ndarray:
    """Status codes of a batch of metrics: feasible, overshoot or settling failing, both,
    diverged."""
    flat = {k: np.asarray(getattr(info, k)) for k in ("settling_time", "overshoot", "diverged")}
    ok = feasible_mask(flat, spec.settling_time, spec.overshoot)
    slow = ~(flat["settling_time"] < spec.settling_time)
    high = ~(flat["overshoot"] < spec.overshoot)
    code = np.where(slow & high, BOTH, np.where(slow, SLOW, OVERSHOOTS))
    code = np.where(ok, FEASIBLE, code)
    return np.where(flat["diverged"], DIVERGED, code).astype(np.int8)


class DesignProblem:
    """The design page's problem: the design plant (the handout's, or the student's), the spec
    and, optionally, the student's recording to overlay.

    plant: the design plant (default :func:`jaxcart.handout_plant`); plant_label: what that
    plant is, as the page names it (e.g. "fitted plant (P.toml)"; None: the handout's; with a
    label the handout plant's run is drawn beside it); overlay: a :class:`Overlay` or None;
    region_points: points per axis of the feasible region."""

    def __init__(
        self,
        plant: jc.Plant | None = None,
        *,
        plant_label: str | None = None,
        overlay: Overlay | None = None,
        spec: Spec = SPEC,
        region_points: int = REGION_POINTS,
    ):
        if (plant is None) != (plant_label is None):
            raise ValueError("give a design plant and its label together (or neither)")
        self.plant = jc.handout_plant() if plant is None else plant
        self.plant_label = plant_label
        self.overlay = overlay
        self.spec = spec
        self.region_points = int(region_points)
        self.nominal_plant = jc.handout_plant() if plant_label is not None else None
        self.region = functools.lru_cache(maxsize=64)(self._region)
        self._plant_systems: dict = {}

    @property
    def start(self) -> Settings:
        """The sliders' first position: the recording's gains and step when it has them, else
        the handout's start (kp 40, ki 5, kd 5) and the spec's 0.5 m step."""
        rec = self.overlay
        if rec is None or rec.controller is None:
            return Settings()
        pid = rec.controller
        lo, hi, _ = RANGES["setpoint"]
        target = float(rec.reference[-1])
        setpoint = target if lo <= target <= hi and target != 0 else SPEC.step
        values = {"kp": pid.kp, "ki": pid.ki, "kd": pid.kd, "tau": pid.tau}
        clipped = {k: float(min(max(v, RANGES[k][0]), RANGES[k][1])) for k, v in values.items()}
        return Settings(**clipped, setpoint=setpoint)

    def experiment(self, setpoint: float):
        return _experiment(float(setpoint), float(self.spec.horizon))

    def design(self, settings: Settings) -> Design:
        """The exact run, metrics, checks and poles at one slider position (in float64,
        whatever the process has set: a page in a notebook computes as the command's does)."""
        with jax.enable_x64(True):
            return self._design(settings)

    def _design(self, settings: Settings) -> Design:
        pid = settings.controller()
        experiment = self.experiment(settings.setpoint)
        response = jc.simulate(self.plant, pid, experiment, solver=EXACT)
        info = None
        if settings.setpoint != 0:
            info = jc.step_info(response, v_limit=V_LIMIT, band=self.spec.band)
        y = np.asarray(response.position, dtype=float)
        excursion = float(np.max(np.abs(y - y[0]))) if np.all(np.isfinite(y)) else math.inf
        checks = checks_of(info, self.spec, excursion) if info is not None else ()
        meets = info is not None and info.meets(self.spec.settling_time, self.spec.overshoot)
        plant_ss = self._plant_ss(pid.sample_time)
        z = loop_poles(self.plant, pid, plant_ss)
        nominal = None
        if self.nominal_plant is not None:
            nominal = jc.simulate(self.nominal_plant, pid, experiment, solver=EXACT)
        return Design(
            settings=settings,
            response=response,
            info=info,
            checks=checks,
            meets=bool(meets) and excursion < TRAVEL,
            poles=s_plane(z, pid.sample_time),
            stable=bool(np.all(np.abs(z) < 1.0)),
            nominal=nominal,
            excursion=excursion,
            margins=margins(self.plant, pid, plant_ss=plant_ss),
        )

    def _plant_ss(self, sample_time: float):
        key = float(sample_time)
        if key not in self._plant_systems:
            self._plant_systems[key] = control_systems.plant_ss(self.plant, key)
        return self._plant_systems[key]

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The region's kp [V/m] and kd [V s/m] axes (the sliders' ranges)."""
        n = self.region_points
        kp_lo, kp_hi, _ = RANGES["kp"]
        kd_lo, kd_hi, _ = RANGES["kd"]
        # kp = 0 is a cart that never moves: start one cell in.
        kp = np.linspace(kp_lo, kp_hi, n + 1)[1:]
        return kp, np.linspace(kd_lo, kd_hi, n)

    def _region(self, ki: float, tau: float, setpoint: float) -> Region:
        kp, kd = self.axes()
        kp_grid, kd_grid = np.meshgrid(kp, kd)  # rows kd, columns kp
        gains = np.stack([kp_grid.ravel(), kd_grid.ravel(), np.full(kp_grid.size, ki)], axis=1)
        base = PID(tau=tau, v_limit=V_LIMIT)
        info = step_metrics_batch(
            self.plant, base, self.experiment(setpoint), gains, dtype=np.float32
        )
        shape = kp_grid.shape
        status = region_status(info, self.spec).reshape(shape)
        return Region(
            kp=kp,
            kd=kd,
            ki=float(ki),
            tau=float(tau),
            setpoint=float(setpoint),
            status=status,
            settling_time=np.asarray(info.settling_time, dtype=float).reshape(shape),
            overshoot=np.asarray(info.overshoot, dtype=float).reshape(shape),
        )

    def region_at(self, settings: Settings) -> Region:
        """The feasible region at the settings' ki, tau and setpoint (memoized: moving kp or
        kd reuses it). At setpoint 0 (no step) the spec's step is used."""
        setpoint = settings.setpoint if settings.setpoint != 0 else self.spec.step
        return self.region(float(settings.ki), float(settings.tau), float(setpoint))


@functools.lru_cache(maxsize=32)
def _experiment(setpoint: float, horizon: float):
    with jax.enable_x64(True):  # the reference in float64 (the grid casts it to its dtype)
        return jc.step(setpoint, horizon=horizon)


def overlay_from(recording) -> Overlay:
    """The page's :class:`Overlay` of a :class:`jaxcart.files.Recording`; a recording that is
    not a closed-loop run is refused in one line."""
    where = f"--data {recording.path}"
    if recording.kind != "closed_loop" or recording.reference is None:
        raise UserError(
            f"{where}: a {recording.kind} experiment; give a closed-loop step recording "
            "(a P, PI or PID step of Parts (iii)-(v)) to overlay on the design page"
        )
    y0 = float(recording.position[0])
    response = recording.as_response()
    info = None
    r = recording.reference
    if np.all(r == r[-1]) and r[-1] != y0:
        info = jc.step_info(response, v_limit=V_LIMIT)
    command = None if recording.command is None else np.asarray(recording.command, dtype=float)
    return Overlay(
        name=recording.path.name,
        time=np.asarray(recording.time, dtype=float) - float(recording.time[0]),
        position=np.asarray(recording.position, dtype=float) - y0,
        reference=np.asarray(r, dtype=float) - y0,
        command=command,
        info=info,
        controller=recording.controller,
        y0=y0,
    )


def problem_from_files(data=None, plant=None, *, region_points: int = REGION_POINTS):
    """The :class:`DesignProblem` of ``jaxcart app --data REC.toml --plant P.toml``: the
    student's plant (closed loop, motor connected) as the design plant, the recording
    overlaid. Each file is checked for what it is first (:func:`design_plant`)."""
    with jax.enable_x64(True):  # read in float64, whatever the process has set
        return _problem_from_files(data, plant, region_points)


def _problem_from_files(data, plant, region_points) -> DesignProblem:
    overlay = None
    if data is not None:
        _refuse_plant_file(data)
        overlay = overlay_from(read_experiment(data))
    design = label = None
    if plant is not None:
        design, label = design_plant(plant)
    return DesignProblem(design, plant_label=label, overlay=overlay, region_points=region_points)


def _toml_head(path) -> dict:
    """The TOML of ``path`` ({} when it is not readable TOML: its reader says why)."""
    try:
        return tomllib.loads(Path(path).read_text(encoding="utf-8-sig"))
    except (tomllib.TOMLDecodeError, OSError, UnicodeDecodeError):
        return {}


def _refuse_plant_file(path) -> None:
    if _toml_head(path).get("format") == FORMAT:
        raise UserError(
            f"--data {path}: a plant file, not a recording; give it as --plant {path}, and a "
            "closed-loop step recording (an experiment file) as --data"
        )


def design_plant(path) -> tuple[jc.Plant, str]:
    """(plant, its label on the page) of ``--plant PATH``: a plant file (from ``jaxcart fit``
    or ``diagnose``: "fitted plant (P.toml)"; without a [fit] table: "plant of P.toml"), or an
    experiment file's own [plant] table ("[plant] of run.toml"). A recording without one
    holds no plant (the handout's would be drawn under another name): refused with the fix."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"--plant {path}: no such file; give a plant file (.toml)")
    head = _toml_head(path)
    if head.get("format") == FORMAT or "kind" not in head:
        # A plant file, or no experiment file either: the plant file's reader says what to fix.
        plant = read_plant_file(path)[0]
        label = f"fitted plant ({path.name})" if "fit" in head else f"plant of {path.name}"
    elif head.get("plant"):
        plant, label = read_experiment(path).plant(), f"[plant] of {path.name}"
    else:
        raise UserError(
            f"--plant {path}: a recording (an experiment file) with no [plant] table, so no "
            f"plant of its own; fit one to it (jaxcart fit {path} --params B_eq,f_c --out "
            f"fitted.toml) and give --plant fitted.toml; to overlay the recording, give it as "
            f"--data {path}"
        )
    # A plant fitted to a tap (motor unplugged) is the same cart: drive it.
    return dataclasses.replace(plant, motor_connected=True), label
