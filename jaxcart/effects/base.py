"""The effect protocol: physics beyond the handout's linear model, with state, in two forms.

Each effect is one frozen dataclass registered as a pytree (its parameters are array leaves: they
can be fitted, vmapped and differentiated; its configuration is static) and acts at one stage of
the sampled loop (docs/design.md, "Effects"):

    controller --u_k--> [voltage stage] --v(t)--> cart: m y'' + c y' = gamma v + F --> y(t)
        ^                                                 [force stage] F(y, y', v)      |
        '--y_meas,k-- [sensor stage] <------------------------- y_k ---------------------'

- ``stage = "voltage"``: maps the command held over one sample to the voltage the motor sees.
  The held voltage is a :class:`Held` profile: ``early`` over [t_k, t_k + split), ``late`` over
  [t_k + split, t_k+1) (``split = 0`` for a plain zero-order hold; a delay moves the edge).
  ``smooth(state, held, smoothing, sample_time) -> (held, state)`` (JAX) and
  ``exact(state, held, sample_time) -> (held, state)`` (Python floats).
- ``stage = "force"``: a force on the cart [N]. Dry friction (Coulomb, stiction, friction along
  the track, ...) is one family: each member gives ``kinetic(y)`` [N] (or, where it differs by
  direction, ``kinetic_sides(y)``: the levels moving right and left), ``static()`` [N] and/or
  ``stribeck()`` [m/s]; the simulators combine them in one Karnopp law (exact) or one smoothed
  law (smooth). Any other
  force gives ``smooth_force(y, yd, v, smoothing, plant)`` (JAX) and ``exact_force(y, yd, v,
  plant)`` (floats), continuous in y and yd (and may give ``exact_force_for(drive)``, the same
  force as a closure with its constants bound, for the exact simulator's inner loop). A
  force effect that splits the moving body in two (``transmission = True``: backlash between
  pinion and rack) has state and owns the motion between samples: the smooth loop carries its
  state and steps a two-body sub-step, the exact simulator a two-body event integrator (see
  :mod:`jaxcart.effects.backlash`).
- ``stage = "sensor"``: maps the cart's position to what the controller reads:
  ``smooth_measure(state, y, smoothing) -> (y_meas, state)`` and ``exact_measure(state, y) ->
  (y_meas, state)``.

State: ``init_state(sample_time)`` returns a tuple of arrays (``()`` for a memoryless effect)
for the smooth simulator, ``exact_init(sample_time)`` its plain-Python twin for the exact one;
both simulators carry every effect's state through the loop.

Each effect declares its parameters once (:class:`Param`: unit, valid range, typical starting
value, the smoothing width it uses). Adding an effect is one module plus one line in
``jaxcart/effects/__init__.py``; the registry below is how the plant spec, the file reader, the
fitter, both simulators and the contract tests find it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

STAGES = ("voltage", "force", "sensor")
#: Order of the stages in listings (the loop itself runs sensor -> controller -> voltage -> force).
STAGE_ORDER = {"sensor": 0, "voltage": 1, "force": 2}
#: Smoothing widths an effect may use (fields of :class:`jaxcart.smoothing.Smoothing`).
WIDTHS = ("voltage", "velocity", "position")


@dataclass(frozen=True)
class Param:
    """What an effect declares about one of its parameters.

    name: the parameter's name in files and fits (unique across effects); unit: SI unit;
    low, high: the valid range (inclusive; ``high`` may be inf); start: a typical starting
    value for a fit; width: the smoothing width its nonsmooth form uses (a field of
    Smoothing) or None; doc: one line; size: 0 for a scalar, n for a vector of n values.
    """

    name: str
    unit: str
    low: float
    high: float
    start: float
    width: str | None = None
    doc: str = ""
    size: int = 0
    #: "drive" (motor and amplifier: acts only with the motor connected, and may differ from
    #: one run to the next as the motor warms and the supply sags), "cart" (the mechanics,
    #: one value for every run of a cart) or "sensor"
    role: str = "cart"
    #: what a cart of this lab has [unit]: a fit is held inside it (None: the valid range)
    plausible: tuple[float, float] | None = None
    #: the value at which the parameter's effect does nothing (None: it always acts);
    #: inf for a limit [unit]
    neutral: float | None = None
    #: the least value worth naming an effect for [unit]: a strength below it is too small
    #: to matter physically, however significant (None: any significant value)
    min_size: float | None = None
    #: what a fit starts it at where the recordings show it, rather than at ``start``:
    #: "held", the largest drive force [N] the recordings held the cart at rest with (a
    #: breakaway level: from a start below it the cart breaks away early and the fit stalls
    #: in another basin), or None
    starts_at: str | None = None

    @property
    def log(self) -> bool:
        """Fitted as its logarithm (relative steps): a parameter that cannot be negative."""
        return self.low >= 0

    @property
    def fit_range(self) -> tuple[float, float]:
        """The bounds of a fit [unit]: the plausible range, else the valid one; strictly
        positive for a parameter fitted as a logarithm."""
        lo, hi = self.plausible if self.plausible is not None else (self.low, self.high)
        if self.log and lo <= 0:
            lo = max(self.start * 1e-4, 1e-12)
        return float(lo), float(hi)

    def check(self, value, where: str) -> None:
        """Raise ValueError naming the parameter, its range and ``where`` if out of range."""
        values = value if isinstance(value, list | tuple) else [value]
        for v in values:
            v = float(v)
            if math.isnan(v) or not (self.low <= v <= self.high):
                high = "inf" if math.isinf(self.high) else f"{self.high:g}"
                raise ValueError(
                    f"{where}: {self.name} = {v!r} {self.unit}: out of its range "
                    f"[{self.low:g}, {high}] {self.unit}"
                )


class Held(NamedTuple):
    """The voltage held over one sample period: ``early`` [V] over [t_k, t_k + split),
    ``late`` [V] over the rest; ``split`` [s] in [0, Ts]."""

    early: Any
    late: Any
    split: Any

    def shifted(self, offset) -> Held:
        """The same profile with ``offset`` [V] added to both pieces (an offset of the drive)."""
        return Held(self.early + offset, self.late + offset, self.split)


class Effect:
    """Base class of effects; subclasses are frozen pytree dataclasses registered with
    :func:`register`."""

    #: registry key and the name in files and diagnoses ("saturation", "coulomb", ...)
    name: ClassVar[str] = ""
    stage: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()
    #: order within its stage (lower first); memoryless voltage effects commute with a delay
    order: ClassVar[int] = 50
    #: True when the effect moves the voltage edge inside the sample (the loop then
    #: integrates two pieces per sample; plain plants pay nothing)
    splits_sample: ClassVar[bool] = False
    #: dry friction (combined by the simulators' Karnopp / smoothed friction law)
    dry_friction: ClassVar[bool] = False
    #: a transmission that splits the moving body in two (backlash); at most one per plant
    transmission: ClassVar[bool] = False
    #: a dry-friction level that depends on the position (the exact simulator then integrates)
    position_dependent: ClassVar[bool] = False
    #: a dry-friction member whose kinetic level differs by direction (``kinetic_sides``)
    sided: ClassVar[bool] = False
    #: one line for listings and reports
    summary: ClassVar[str] = ""
    #: why the effect is not a candidate of the diagnosis's structure search ("": it is)
    not_candidate: ClassVar[str] = ""
    #: the least stretch of track [m] the recordings must cover together (the range of their
    #: positions) for the effect to be a candidate: a map of the position needs the positions
    #: (0: any recording; tuning.estimation.engine.parameters.candidates)
    covers: ClassVar[float] = 0.0
    #: the other data conditions the recordings must meet for the effect to be a candidate
    #: (tuning.estimation.engine.coverage.NEEDS: "both_ways", the cart slides both ways;
    #: "drive_both_ways", the drive pushes both ways; "tap", a tap among the recordings)
    needs: ClassVar[tuple[str, ...]] = ()
    #: effects whose parameters a candidate of this one frees and names too (stiction is
    #: static friction above a kinetic level: it stands on Coulomb friction)
    requires: ClassVar[tuple[str, ...]] = ()
    #: the largest signal of a run a limit caps ("command" [V], "current" [A]): a limit above
    #: it never acts, and its strength is how far below it the limit lies
    limits: ClassVar[str] = ""
    #: the signals a residual left by this effect's absence correlates with (a diagnosis's
    #: regressor tests: "command", "sign_velocity", "position", "acceleration")
    shows_in: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def drive_only(cls) -> bool:
        """True when every parameter belongs to the drive: the effect needs the motor."""
        return all(p.role == "drive" for p in cls.params)

    @classmethod
    def consistent(cls, values: dict) -> dict:
        """``values`` [SI] made consistent with the effect's own constraints (default: as
        given); a fit's trial values pass through it before they are simulated exactly."""
        return values

    @classmethod
    def strengths(cls, values: dict, peaks: dict):
        """How far each item this effect names is from doing nothing: yields (item, strength,
        weights of the parameters in it, what it measures, where it does nothing). Positive
        when it acts; ``peaks``: {"command": largest |command| [V], "current": largest
        |armature current| [A]} of the run, for a limit. By default each scalar parameter with
        a neutral value: a limit's distance below the run's peak, a parameter valid on either
        side of its neutral value (an asymmetry, an offset) its distance from it, any other
        its excess over it."""
        for p in cls.params:
            if p.neutral is None or p.size:
                continue
            v = values[p.name]
            if cls.limits:
                top = peaks.get(cls.limits, math.inf)
                yield (
                    cls.name,
                    top - v,
                    {p.name: -1.0},
                    f"{p.name} = {v:.3g} {p.unit}",
                    f"the largest {cls.limits}, {top:.3g} {p.unit}",
                )
            elif p.low < p.neutral:
                # Acts on either side of its neutral value (an asymmetry, an offset): the
                # distance from it, whichever way.
                zero = f"{p.neutral:g} {p.unit}"
                sign = 1.0 if v >= p.neutral else -1.0
                what = f"|{p.name}| = {abs(v - p.neutral):.3g} {p.unit}"
                yield cls.name, abs(v - p.neutral), {p.name: sign}, what, zero
            else:
                zero = f"{p.neutral:g} {p.unit}"
                yield cls.name, v - p.neutral, {p.name: 1.0}, f"{p.name} = {v:.3g} {p.unit}", zero

    @classmethod
    def param_names(cls) -> tuple[str, ...]:
        return tuple(p.name for p in cls.params)

    @classmethod
    def param(cls, name: str) -> Param:
        return next(p for p in cls.params if p.name == name)

    def values(self) -> dict:
        """{parameter name: value} of this effect."""
        return {p.name: getattr(self, p.name) for p in self.params}

    def init_state(self, sample_time: float) -> tuple:
        """Initial state (a tuple of arrays; empty for a memoryless effect)."""
        return ()

    def exact_init(self, sample_time: float):
        """Initial state for the exact simulator (Python values)."""
        return ()

    def check(self, sample_time: float) -> None:
        """Raise ValueError if the effect cannot run at this sample time (e.g. a delay longer
        than its line)."""

    # Dry friction (only where dry_friction is True).
    def kinetic(self, y, xp):
        """Kinetic friction level [N] at position y (0 if the effect has none)."""
        return 0.0

    def kinetic_sides(self, y, xp):
        """(level moving right, level moving left) [N] at position y: :meth:`kinetic` both
        ways unless the effect is ``sided``. The simulators sum each side over the members and
        hold a sum below 0 at 0 (friction never pushes)."""
        level = self.kinetic(y, xp)
        return level, level

    def exact_kinetic_sides(self):
        """``y -> (right, left)`` [N]: :meth:`kinetic_sides` on Python floats, for the exact
        simulator, which asks ~10^6 times a run where a level varies; an effect may return a
        closure with its constants computed once, the same arithmetic (bit for bit)."""
        return lambda y: self.kinetic_sides(y, math)

    def static(self):
        """Static (breakaway) level [N], or None if the effect has none."""
        return None

    def stribeck(self):
        """The Stribeck speed [m/s] over which the friction falls from the static level to the
        kinetic one as the cart speeds up, or None (the Karnopp jump at breakaway)."""
        return None

    # Other forces (stage "force", with exact_force).
    def exact_force_for(self, drive):
        """``f(y, yd, v)`` [N]: :meth:`exact_force` with the drive bound. The exact
        simulator's RK4 calls it 80 times a sample; an effect may return a closure with its
        constants computed once, the same arithmetic (bit for bit)."""
        force = self.exact_force
        return lambda y, yd, v: force(y, yd, v, drive)

    def exact_affine(self, drive):
        """(k_y [N/m], k_yd [N s/m], f0 [N]) where the exact force is F = k_y y + k_yd y' + f0
        at every voltage, or None (the default: not affine). The exact simulator then steps a
        whole sample in one affine map instead of its RK4 sub-steps (jaxcart.exact)."""
        return None

    # An effect whose exact force is piecewise linear in the velocity alone, at a held voltage,
    # may also give ``exact_velocity_pieces(drive, v)`` -> (breaks, pieces): the velocities
    # [m/s] where its law changes, ascending, and for each of the len(breaks) + 1 intervals
    # (f0 [N], k [N s/m]) with F = f0 + k y'. The exact simulator then solves the cart in
    # closed form between events instead of by RK4 (jaxcart.exact._VelocityCart).


def within(values: dict, name: str, bound: str) -> dict:
    """``values`` with ``name`` held within +-``values[bound]`` where both are given: an
    asymmetry no larger than the symmetric level it splits (both sides' levels stay >= 0)."""
    if name in values and bound in values:
        top = abs(values[bound])
        values = {**values, name: min(max(values[name], -top), top)}
    return values


#: Registered effect classes by name, in registration order.
REGISTRY: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Add an effect class to the registry (its name and parameter names must be new)."""
    if cls.stage not in STAGES:
        raise TypeError(f"effect {cls.__name__}: stage {cls.stage!r} is not one of {STAGES}")
    if not cls.name or cls.name in REGISTRY:
        raise TypeError(f"effect {cls.__name__}: name {cls.name!r} is empty or taken")
    taken = {p: n for n, c in REGISTRY.items() for p in c.param_names()}
    for p in cls.params:
        if p.name in taken:
            raise TypeError(f"effect {cls.name}: parameter {p.name} belongs to {taken[p.name]}")
        if p.width is not None and p.width not in WIDTHS:
            raise TypeError(f"effect {cls.name}: width {p.width!r} is not one of {WIDTHS}")
    REGISTRY[cls.name] = cls
    return cls


def effect_of_param(name: str) -> type[Effect] | None:
    """The registered effect class that owns a parameter name, or None."""
    for cls in REGISTRY.values():
        if name in cls.param_names():
            return cls
    return None
