"""How far a design is from trouble on the cart: the margins of the sampled loop with its delay,
the voltage ripple the encoder causes, and whether integral action will hunt.

    r --(+)--> C(z) --u--> [ delay, ZOH cart P(z) ] --+--> y        L(z) = C(z) P(z)
         |-                                           |             S(z) = 1 / (1 + L(z))
         '--------------------------------------------'

- gain margin: the factor by which every gain (kp, ki, kd together) may grow before the loop
  is unstable; phase margin [deg] at the gain crossover; delay margin: the further transport
  delay [s] it tolerates (phase margin / crossover frequency); peak sensitivity Ms = max |S|
  (1.2-2 is the usual range; 1/Ms is the least distance of the Nyquist curve from -1). All on
  the loop's linear part as the hardware runs it: the cart sampled with a zero-order hold
  behind its fitted delay (its state space from :mod:`jaxcart.control_systems`), and the PID
  exactly, its frequency response on a log grid up to the Nyquist frequency pi/Ts and the
  crossovers interpolated on it (``tests/test_margins.py`` holds them to python-control's
  margins and to the closed loop's eigenvalues; a few milliseconds, for the design page).
  Friction, the drive's limits and the encoder are left out: the margins describe the loop
  while the command stays inside its limits.
- ripple: the change of the command when the encoder reads one count more, within one sample,
  q (kp + kd/(tau + Ts)) [V] (the PID's immediate response to a step of one count q: an
  unfiltered kd = 9 V s/m turns 2.275e-5 m into 0.2 V); a position that sits between two counts
  toggles the command by that much.
- hunting: with integral action (ki > 0) and static friction above the kinetic (f_s > f_c),
  the cart sticks short of the target, the integral builds the command up to the breakaway
  level and the cart lurches past: a stick-slip cycle about the target that never settles.

>>> import jaxcart as jc
>>> m = margins(jc.handout_plant(), jc.PID(kp=40.0, kd=5.0, ki=5.0))
>>> bool(m.phase_margin > 30.0), bool(m.peak_sensitivity < 2.0)
(True, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import control
import numpy as np

from jaxcart import control_systems as cs
from jaxcart.effects import Quantization
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.plausibility import plant_delay

#: Points of the frequency grid, log-spaced from :data:`LOWEST` [rad/s] to pi/Ts.
GRID = 2000
LOWEST = 1e-2
#: The encoder's parameter (its count [m]).
COUNT = Quantization.params[0].name


@dataclass(frozen=True)
class Margins:
    """The margins of one design on one cart (module docstring).

    gain_margin: factor [-] (inf: no phase crossover); phase_margin [deg]; gain_crossover and
    phase_crossover [rad/s] (nan where there is none); delay_margin [s]; peak_sensitivity Ms
    [-] at peak_frequency [rad/s]; delay: the loop's transport delay [s]; ripple: one
    encoder count's change of the command within a sample [V]; count: the encoder's count [m];
    hunting: the warning, or "" (integral action without static friction above the kinetic).
    """

    gain_margin: float
    phase_margin: float
    gain_crossover: float
    phase_crossover: float
    delay_margin: float
    peak_sensitivity: float
    peak_frequency: float
    delay: float
    ripple: float
    count: float
    hunting: str = ""

    @property
    def gain_margin_db(self) -> float:
        return 20.0 * math.log10(self.gain_margin) if self.gain_margin > 0 else -math.inf

    def to_json(self) -> dict:
        out = {k: _plain(getattr(self, k)) for k in self.__dataclass_fields__ if k != "hunting"}
        out["gain_margin_db"] = _plain(self.gain_margin_db)
        out["hunting"] = self.hunting
        return out

    def lines(self) -> list[str]:
        """The margins in words, one line each (the tuner's printout, the report)."""
        gm = (
            "no phase crossover (gain margin infinite)"
            if not math.isfinite(self.gain_margin)
            else f"gain margin {self.gain_margin:.3g} ({self.gain_margin_db:.1f} dB)"
        )
        out = [
            f"{gm}, phase margin {self.phase_margin:.1f} deg at {self.gain_crossover:.3g} "
            f"rad/s (a further {self.delay_margin * 1e3:.3g} ms of delay), peak sensitivity "
            f"{self.peak_sensitivity:.2f} at {self.peak_frequency:.3g} rad/s; the sampled "
            + (f"loop with its {self.delay * 1e3:.3g} ms delay" if self.delay else "loop"),
            f"ripple: one encoder count ({self.count * 1e3:.4g} mm) moves the command by "
            f"{self.ripple:.3g} V within a sample",
        ]
        return out + ([self.hunting] if self.hunting else [])


def _plain(x):
    x = float(x)
    return x if math.isfinite(x) else ("inf" if x > 0 else "-inf" if x < 0 else "nan")


def loop_transfer(plant, pid) -> control.TransferFunction:
    """L(z) = C(z) P(z) as a python-control system: the PID and the ZOH cart behind its delay,
    Ts = the PID's (what the margins are python-control's margins of; the tests compare)."""
    return cs.controller_tf(pid) * cs.plant_tf(plant, pid.sample_time)


def loop_response(plant, pid, omega, plant_ss=None) -> np.ndarray:
    """L(e^{j w Ts}) at the frequencies ``omega`` [rad/s]: the sampled cart behind its delay
    from its state space (:func:`jaxcart.control_systems.plant_ss`, or ``plant_ss`` given),
    C (zI - A)^-1 B + D, times the PID's transfer function
    kp + ki Ts/(z - 1) + kd (z - 1)/((tau + Ts) z - tau) (:mod:`hw.control_law`)."""
    ts = float(pid.sample_time)
    sys = cs.plant_ss(plant, ts) if plant_ss is None else plant_ss
    z = np.exp(1j * np.asarray(omega, dtype=float) * ts)
    n = sys.A.shape[0]
    resolvent = z[:, None, None] * np.eye(n)[None] - sys.A[None]
    x = np.linalg.solve(resolvent, np.broadcast_to(sys.B, (z.size, n, 1)).astype(complex))
    p = (sys.C @ x)[:, 0, 0] + sys.D[0, 0]
    kp, ki, kd, tau = (float(getattr(pid, k)) for k in ("kp", "ki", "kd", "tau"))
    c = kp + ki * ts / (z - 1.0) + kd * (z - 1.0) / ((tau + ts) * z - tau)
    return c * p


def _crossings(x, y) -> list[float]:
    """Where ``y`` changes sign along ``x`` (linear between the points)."""
    i = np.flatnonzero(np.sign(y[:-1]) * np.sign(y[1:]) < 0)
    return [float(x[k] - y[k] * (x[k + 1] - x[k]) / (y[k + 1] - y[k])) for k in i]


def crossovers(omega, response) -> tuple[float, float, float, float]:
    """(gain margin, phase crossover [rad/s], phase margin [deg], gain crossover [rad/s]) of a
    frequency response: the least gain margin above 1 (where the phase crosses -180 deg, the
    imaginary part changes sign with the real part negative) and the least phase margin (at
    each frequency where |L| crosses 1), each interpolated linearly in log frequency."""
    logw = np.log(omega)
    gm, wpc = math.inf, math.nan
    for lw in _crossings(logw, response.imag):
        value = np.interp(lw, logw, response.real) + 1j * np.interp(lw, logw, response.imag)
        if value.real < 0 and 1.0 / abs(value) > 1.0 and 1.0 / abs(value) < gm:
            gm, wpc = 1.0 / abs(value), math.exp(lw)
    pm, wgc = math.inf, math.nan
    phase = np.unwrap(np.angle(response))
    for lw in _crossings(logw, np.log(np.abs(response))):
        margin = (math.degrees(np.interp(lw, logw, phase)) + 180.0 + 180.0) % 360.0 - 180.0
        if margin < pm:
            pm, wgc = margin, math.exp(lw)
    return gm, wpc, pm, wgc


def ripple(pid, count: float = ENCODER_RESOLUTION) -> float:
    """One encoder count's change of the command within one sample, q (kp + kd/(tau + Ts))
    [V] (``count``: q [m])."""
    return float(count) * (float(pid.kp) + float(pid.kd) / (float(pid.tau) + pid.sample_time))


def encoder_count(plant) -> float:
    """The cart's encoder count [m] (its fitted one where it has an encoder effect)."""
    if COUNT in plant.param_names():
        return float(plant.get(COUNT))
    return ENCODER_RESOLUTION


def hunting(plant, pid) -> str:
    """The warning that integral action hunts with static friction above the kinetic, or ""."""
    names = plant.param_names()
    if float(pid.ki) <= 0 or "f_s" not in names:
        return ""
    f_s = float(plant.get("f_s"))
    f_c = float(plant.get("f_c")) if "f_c" in names else 0.0
    if f_s <= f_c:
        return ""
    return (
        f"integral action with stiction hunts: the cart sticks short of the target, the "
        f"integral (ki = {float(pid.ki):.3g} V/(m s)) builds the command up until the force "
        f"breaks away at f_s = {f_s:.3g} N, and the cart slides past as friction drops to "
        f"f_c = {f_c:.3g} N: a stick-slip cycle about the target. Use ki = 0 (PD: an error "
        f"within f_c/(kp gamma)) or a ki small enough that the cycle outlasts the run"
    )


def margins(plant, pid, *, plant_ss=None) -> Margins:
    """The :class:`Margins` of ``pid`` on ``plant`` (its linear part, delay included;
    ``plant_ss``: its sampled state space where the caller keeps it). The gain margin is the
    factor by which the gains may grow (a loop with integral action on the cart is stable only
    above some gain too: that lower margin is not the one reported); the phase margin the
    least over the gain crossovers."""
    ts = float(pid.sample_time)
    omega = np.geomspace(LOWEST, math.pi / ts * (1 - 1e-6), GRID)
    response = loop_response(plant, pid, omega, plant_ss)
    gm, wpc, pm, wgc = crossovers(omega, response)
    sensitivity = np.abs(1.0 / (1.0 + response))
    peak = int(np.argmax(sensitivity))
    delay_margin = math.radians(pm) / wgc if wgc > 0 and math.isfinite(pm) else math.inf
    count = encoder_count(plant)
    return Margins(
        gain_margin=float(gm),
        phase_margin=float(pm),
        gain_crossover=float(wgc),
        phase_crossover=float(wpc),
        delay_margin=delay_margin,
        peak_sensitivity=float(sensitivity[peak]),
        peak_frequency=float(omega[peak]),
        delay=plant_delay(plant),
        ripple=ripple(pid, count),
        count=count,
        hunting=hunting(plant, pid),
    )
