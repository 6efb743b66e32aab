"""A simulated cart for the loop: the handout's plant with the effects a real cart has.

    u_k --> [delay d samples] --> [amplifier: clip to v_sat] --v--> ZOH --> cart --> y
                                                                                     |
    y_k <-- [encoder: floor(y / q) q, zeroed at the start] <-------------------------'

    cart:  m y'' + c y' = gamma v - F_c,   m = M + M_J,  c = B_eq + B_emf   (handout appendix)
    F_c:   Karnopp stick-slip: stuck while |gamma v| <= f_s, else f_c sgn(y') (kinetic)

Numpy and the standard library only, written independently of jaxcart (hw never imports it).
Between samples the drive is constant and, within a slip phase, so is the friction, so each
phase is solved in closed form (exponential and phi functions, series for small a t); the time
at which the velocity reaches 0 is closed form too, so stick-slip is exact per sample.

>>> cart = SimCart(CartParams(f_c=0.3, quantization=0.0))
>>> cart.start(0.001); cart.read()
0.0
>>> cart.write(6.0); round(cart.read() * 1e6, 3)  # [um] after 1 ms at 6 V
4.659
"""

from __future__ import annotations

import json
import math
import tomllib
from collections import deque
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from hw.devices.base import DeviceError
from hw.handout import APPENDIX, VALID
from hw.handout import ENCODER_RESOLUTION as ENCODER_RESOLUTION

_SERIES_BELOW = 0.5
_PHI2_SERIES = tuple((-1.0) ** n / math.factorial(n + 2) for n in range(16))
_MAX_EVENTS = 8


@dataclass(frozen=True)
class CartParams:
    """Parameters of the simulated cart (SI units; handout appendix by default).

    M: cart + weight mass [kg]; B_eq: viscous friction [kg/s]; f_c: kinetic Coulomb friction
    [N]; f_s: static friction [N] (None: equal to f_c); v_sat: amplifier saturation [V] (inf:
    none); delay: input delay [s], a whole number of samples; quantization: encoder resolution
    [m/count] (0: exact position); gamma_scale: amplifier gain error [-]; Rm [ohm], Kt [N m/A],
    Km [V s/rad], Jm [kg m^2], Kg [-], r_mp [m], eta_g, eta_m [-]: motor and gearbox;
    motor_connected: false for a tap (no back-EMF, no drive).
    """

    M: float = APPENDIX["M"]
    B_eq: float = APPENDIX["B_eq"]
    f_c: float = 0.0
    f_s: float | None = None
    v_sat: float = 6.0
    delay: float = 0.0
    quantization: float = ENCODER_RESOLUTION
    gamma_scale: float = APPENDIX["gamma_scale"]
    Rm: float = APPENDIX["Rm"]
    Kt: float = APPENDIX["Kt"]
    Km: float = APPENDIX["Km"]
    Jm: float = APPENDIX["Jm"]
    Kg: float = APPENDIX["Kg"]
    r_mp: float = APPENDIX["r_mp"]
    eta_g: float = APPENDIX["eta_g"]
    eta_m: float = APPENDIX["eta_m"]
    motor_connected: bool = True

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "motor_connected":
                if not isinstance(value, bool):
                    raise ValueError(f"motor_connected = {value!r}: give true or false")
                continue
            if value is None and f.name == "f_s":
                continue
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"{f.name} = {value!r}: give a number (SI units)")
            if math.isnan(value) or (math.isinf(value) and f.name != "v_sat"):
                raise ValueError(f"{f.name} = {value!r}: give a finite number")
            if f.name in ("M", "Rm", "Kg", "r_mp", "eta_g", "eta_m", "v_sat") and not value > 0:
                raise ValueError(f"{f.name} = {value!r}: it must be positive")
            if not value >= 0:
                raise ValueError(f"{f.name} = {value!r}: it must be >= 0")
            low, high = VALID.get(f.name, (-math.inf, math.inf))
            if not low <= value <= high:
                raise ValueError(
                    f"{f.name} = {value!r}: out of its range [{low:g}, {high:g}] (SI units: "
                    "kg, kg/s, N, V, s)"
                )

    @property
    def m(self) -> float:
        """Moving mass M + M_J [kg]."""
        return self.M + self.eta_g * self.Kg**2 * self.Jm / self.r_mp**2

    @property
    def B_emf(self) -> float:
        """Back-EMF damping [kg/s] (0 with the motor unplugged)."""
        if not self.motor_connected:
            return 0.0
        return self.eta_g * self.Kg**2 * self.eta_m * self.Kt * self.Km / (self.Rm * self.r_mp**2)

    @property
    def c(self) -> float:
        """Total viscous damping B_eq + B_emf [kg/s]."""
        return self.B_eq + self.B_emf

    @property
    def gamma(self) -> float:
        """Force per volt [N/V] (0 with the motor unplugged)."""
        if not self.motor_connected:
            return 0.0
        return (
            self.gamma_scale * self.eta_g * self.Kg * self.eta_m * self.Kt / (self.Rm * self.r_mp)
        )

    def to_dict(self) -> dict:
        """The parameters as plain values (f_s omitted when None), for [device]."""
        return {k: v for k, v in asdict(self).items() if v is not None}


NAMES = tuple(f.name for f in fields(CartParams))


def cart_params(values: dict, where: str = "cart parameters") -> CartParams:
    """:class:`CartParams` from ``{name: value}``; one-line errors that name ``where``."""
    unknown = [k for k in values if k not in NAMES]
    if unknown:
        raise DeviceError(f"{where}: unknown parameter {unknown[0]!r}; known: {', '.join(NAMES)}")
    try:
        return CartParams(**values)
    except (ValueError, TypeError) as exc:
        raise DeviceError(f"{where}: {exc}") from None


def load_cart_params(path) -> CartParams:
    """Cart parameters from a TOML or JSON file of ``name = value`` (a [plant] table is read if
    there is one), e.g. ``B_eq = 4.6``, ``f_c = 0.45``, ``delay = 0.002``."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise DeviceError(f"{path}: cannot read it ({exc.strerror})") from None
    try:
        if path.suffix.lower() == ".json":
            values = json.loads(text)
        else:
            values = tomllib.loads(text.decode("utf-8-sig"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise DeviceError(
            f"{path}: not a TOML or JSON file ({' '.join(str(exc).split())})"
        ) from None
    if isinstance(values, dict) and values.get("format") == "jaxcart-plant":
        return _from_plant_file(values, path)
    if isinstance(values, dict) and isinstance(values.get("plant"), dict):
        values = values["plant"]
    if not isinstance(values, dict):
        raise DeviceError(f"{path}: expected a table of name = value")
    return cart_params(values, str(path))


#: The cart's effect parameters (the names of their fields in CartParams and in a jaxcart plant
#: file's [effects.NAME] tables) at the values where each does nothing: a plant file that names
#: no table holding one leaves it there (no amplifier limit, no friction, no delay, an exact
#: encoder). Written as keywords because hw never imports jaxcart's effects registry.
ABSENT_EFFECT = dict(v_sat=math.inf, f_c=0.0, f_s=None, delay=0.0, quantization=0.0)


#: The top-level keys of a plant file (jaxcart.plantspec writes and reads the same).
PLANT_FILE_KEYS = {"format", "version", "motor_connected", "structure", "effects", "plant", "fit"}


def _from_plant_file(doc: dict, path) -> CartParams:
    """Cart parameters from a plant file (``jaxcart fit --out``, ``diagnose``): its [plant]
    table and its [effects.NAME] tables; an effect it names is in the cart, one it does not
    name is absent (no amplifier limit, no friction, exact encoder). The cart models an
    effect whose table holds only parameters of :data:`ABSENT_EFFECT`."""
    stray = sorted(set(doc) - PLANT_FILE_KEYS)
    if stray:
        raise DeviceError(
            f"{path}: unknown key {stray[0]!r}; allowed: {', '.join(sorted(PLANT_FILE_KEYS))} "
            "(the cart's values go in a [plant] table)"
        )
    values = dict(doc.get("plant", {}))
    effects = doc.get("effects", {})
    other = sorted(
        name
        for name, table in effects.items()
        if not isinstance(table, dict) or set(table) - set(ABSENT_EFFECT)
    )
    if other:
        raise DeviceError(
            f"{path}: the simulated cart does not model {', '.join(other)}; it models the "
            f"effects whose parameters are among {', '.join(ABSENT_EFFECT)}"
        )
    for name, neutral in ABSENT_EFFECT.items():
        if neutral is not None:  # f_s None: the cart's own default (equal to f_c)
            values.setdefault(name, neutral)
    for table in effects.values():
        values.update(table)
    values.setdefault("motor_connected", doc.get("motor_connected", True))
    return cart_params(values, str(path))


def _phis(a: float, t: float) -> tuple[float, float, float]:
    """e^{-a t}, (1 - e^{-a t})/a, (t - phi1)/a: over a phase of length t with y'' = -a y' + b,
    y'(t) = e y'_0 + phi1 b and y(t) = y_0 + phi1 y'_0 + phi2 b (exact at a = 0)."""
    x = a * t
    if x == 0.0:
        return 1.0, t, 0.5 * t * t
    em = -math.expm1(-x)
    if x < _SERIES_BELOW:  # (x - 1 + e^-x)/x^2 cancels for small x: its Taylor series instead
        g = 0.0
        for coef in reversed(_PHI2_SERIES):
            g = g * x + coef
    else:
        g = (x - em) / (x * x)
    return 1.0 - em, t * em / x, t * t * g


class SimCart:
    """The simulated cart as a device (virtual time or paced by the loop's clock).

    ``position`` and ``velocity`` are the true state [m, m/s]; ``read()`` returns the encoder's
    view of the position, zeroed at ``start``.
    """

    name = "sim"
    hardware_timed = False
    virtual = True

    def __init__(self, params: CartParams | None = None):
        self.params = params or CartParams()
        self.last_voltage = 0.0
        self.position = self.velocity = 0.0
        self._started = False

    def start(self, sample_time: float) -> None:
        p = self.params
        self.sample_time = h = float(sample_time)
        steps = p.delay / h
        if abs(steps - round(steps)) > 1e-6:
            raise DeviceError(
                f"sim delay = {p.delay!r} s is not a whole number of samples of {h} s; "
                f"give a multiple of the sample time"
            )
        self._queue = deque([0.0] * int(round(steps)))
        self._m, self._a, self._gain = p.m, p.c / p.m, p.gamma
        self._f_k = p.f_c
        # Break away only when the drive also beats kinetic friction (no chatter).
        self._f_break = max(p.f_c if p.f_s is None else p.f_s, p.f_c)
        self._full = _phis(self._a, h)
        self._q = p.quantization
        self._zero = self.position
        self._force = 0.0
        self._first = True
        self._started = True
        self.last_voltage = 0.0

    def read(self) -> float:
        if not self._started:
            raise DeviceError("sim: read before start")
        if self._first:
            self._first = False
        else:
            self.position, self.velocity = self._advance(self.position, self.velocity)
        y = self.position - self._zero
        if self._q > 0.0:
            return math.floor(y / self._q) * self._q
        return y

    def write(self, volts: float) -> None:
        volts = float(volts)
        self.last_voltage = volts
        if not self._started:
            return  # nothing drives the cart before start
        if self._queue:
            self._queue.append(volts)
            volts = self._queue.popleft()
        v_sat = self.params.v_sat
        self._force = self._gain * min(max(volts, -v_sat), v_sat)

    def stop(self) -> None:
        if self._started:
            self.write(0.0)
            self._queue = deque([0.0] * len(self._queue))
        self.last_voltage = 0.0

    def describe(self) -> dict:
        return {"name": self.name, **self.params.to_dict()}

    # -- the physics

    def _advance(self, y: float, v: float) -> tuple[float, float]:
        """(y, y') one sample later under the held drive (Karnopp stick-slip, closed form)."""
        force, m, a, f_k = self._force, self._m, self._a, self._f_k
        left = self.sample_time
        if f_k == 0.0 and self._f_break == 0.0:
            e, p1, p2 = self._full
            b = force / m
            return y + p1 * v + p2 * b, e * v + p1 * b
        for _ in range(_MAX_EVENTS):
            if v == 0.0:
                if abs(force) <= self._f_break:
                    return y, 0.0  # stuck until the drive changes
                s = 1.0 if force > 0.0 else -1.0
            else:
                s = 1.0 if v > 0.0 else -1.0
            b = (force - s * f_k) / m
            if s * b < 0.0:
                x = -a * v / b  # time to stop: log1p(x)/x * (-v/b), stable as a -> 0
                t_stop = (-v / b) * (1.0 if x == 0.0 else math.log1p(x) / x)
                if t_stop < left:
                    e, p1, p2 = _phis(a, t_stop)
                    y, v = y + p1 * v + p2 * b, 0.0
                    left -= t_stop
                    continue
            e, p1, p2 = self._full if left == self.sample_time else _phis(a, left)
            y, v_end = y + p1 * v + p2 * b, e * v + p1 * b
            return y, (v_end if v_end * s >= 0.0 else 0.0)
        raise RuntimeError(f"more than {_MAX_EVENTS} stick-slip events in one sample")
