"""What a fit returns: each value with its standard errors (:class:`Estimate`), each
recording's fit (:class:`SegmentFit`), the whole (:class:`FitResult`) and its JSON."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from jaxcart.params import Plant
from jaxcart.plantspec import handout_plant
from jaxcart.smoothing import Smoothing
from tuning.estimation.engine import parameters
from tuning.estimation.engine.parameters import base_name
from tuning.estimation.engine.smooth_runs import replacements
from tuning.estimation.fitting.names import canonical, unit_of, with_values


@dataclass(frozen=True)
class Estimate:
    """One fitted value: value [SI] and its standard error (HAC, see the module docstring);
    both None when the parameter is not identifiable from the data (``note`` says why)."""

    name: str
    value: float | None
    stderr: float | None
    identifiable: bool = True
    stderr_naive: float | None = None
    note: str = ""
    held_at: float | None = None  # the value a parameter not identified is held at [SI]
    #: ("upper" | "lower", bound [SI]) where the value sits on an edge of the range the fit
    #: holds it in (engine.parameters.at_edge): then it is no estimate
    edge: tuple | None = None

    @property
    def edge_note(self) -> str:
        """One line saying the value is on an edge of its range ("" when it is not)."""
        if self.edge is None:
            return ""
        side, _ = self.edge
        lo, hi = parameters.bounds(canonical(base_name(self.name)))
        unit = unit_of(self.name)
        return (
            f"{self.name} = {self.value:.4g} {unit} is at the {side} edge of its allowed range "
            f"[{lo:.4g}, {hi:.4g}] {unit}: the data push it beyond what the fit allows, so it "
            "is no estimate (a step recorded late, data in other units, or an effect left "
            "out: jaxcart diagnose)"
        )

    def to_json(self) -> dict:
        out = {"value": _finite(self.value), "stderr": _finite(self.stderr)}
        if self.edge is not None:
            out["at_edge"] = {"side": self.edge[0], "bound": self.edge[1]}
        if not self.identifiable:
            out["identifiable"] = False
            out["note"] = self.note
            if self.held_at is not None:
                out["held_at"] = _finite(self.held_at)
        else:
            out["stderr_naive"] = _finite(self.stderr_naive)
        return out


@dataclass(frozen=True, eq=False)
class SegmentFit:
    """The fit seen on one segment: the measured positions and the model's before and after
    (smooth at the narrowest width, and exact) [m], their RMS errors [m], fitted nuisance;
    held_out: the values [SI] of the fit that left this recording out (its own drive values
    fitted to it alone; in the fit's names, ``v_sat@2``), None where it was not held out."""

    name: str
    kind: str
    time: np.ndarray
    measured: np.ndarray
    before: np.ndarray
    after: np.ndarray
    before_exact: np.ndarray | None
    after_exact: np.ndarray | None
    nuisance: dict
    plant: Plant
    held_out: dict | None = None

    @property
    def rms_before(self) -> float:
        return _rms(self.before - self.measured)

    @property
    def rms_after(self) -> float:
        return _rms(self.after - self.measured)

    @property
    def rms_before_exact(self) -> float | None:
        return None if self.before_exact is None else _rms(self.before_exact - self.measured)

    @property
    def rms_after_exact(self) -> float | None:
        return None if self.after_exact is None else _rms(self.after_exact - self.measured)


@dataclass(frozen=True, eq=False)
class FitResult:
    """The outcome of :func:`fit`.

    params: {name as asked: :class:`Estimate`}; values: every plant value the fit used, by
    canonical name (fitted, or held) [SI]; segments: a :class:`SegmentFit` per recording;
    correlation: {(a, b): correlation} of the identified parameters; n_data: samples fitted;
    seconds: wall time [s]; smoothing: the narrowest smoothing used (None for a diagnosis's
    fit, whose values are the exact simulator's); history: (width [m/s],
    Levenberg-Marquardt iterations, RMS [m]) per width (at the narrowest, of the run kept:
    the continuation's or the direct start's); exact_polish: True when the last polish
    ran on the exact simulator; stages: each optimizer run ({"stage", "iterations", "cap",
    "converged"}, and "superseded": True for the continuation's runs where the direct start
    at the narrowest width was kept instead: they do not count for ``converged``);
    noise_floor: the RMS error [m] a correct model would leave (encoder count q/sqrt(12) and
    white noise); n_effective: independent samples the final residual is worth
    (:func:`effective_samples`); misfit: why the model does not explain the data ("" when it
    does: RMS within :data:`MISFIT_RATIO` of the noise floor), in which case the standard errors
    are widened to what the residual supports.
    """

    params: dict
    values: dict
    segments: list
    correlation: dict
    n_data: int
    seconds: float
    smoothing: Smoothing | None
    history: list = field(default_factory=list)
    exact_polish: bool = False
    stages: list = field(default_factory=list)
    noise_floor: float = 0.0
    n_effective: float = 0.0
    misfit: str = ""
    #: The fitted plant itself, effects included, where the fit made one (a diagnosis's chosen
    #: structure, :attr:`tuning.estimation.diagnose.result.Diagnosis.fit`); None: from ``values``.
    cart: Plant | None = None

    @property
    def converged(self) -> bool:
        """False when an optimizer stopped at its iteration cap (the fit may be unfinished)."""
        return all(
            s["converged"]
            for s in self.stages
            if not s.get("superseded") and not s.get("intermediate")
        )

    @property
    def warnings(self) -> list[str]:
        """One line for each thing the numbers do not show: a model that does not explain the
        data, a parameter held at its start value, an optimizer stopped at its cap."""
        out = [self.misfit] if self.misfit else []
        out += [e.edge_note for e in self.params.values() if e.edge is not None]
        held = {n: e for n, e in self.params.items() if not e.identifiable}
        for n, e in held.items():
            out.append(f"{n}: {e.note}; the other errors are conditional on that value")
        for s in self.stages:
            if not s["converged"] and not s.get("superseded") and not s.get("intermediate"):
                out.append(
                    f"{s['stage']} stopped at its iteration cap ({s['cap']}) before converging; "
                    "the values may not be the best fit"
                )
        return out

    def _total(self, attr) -> float | None:
        parts = [(getattr(s, attr), s.measured.size) for s in self.segments]
        if any(v is None for v, _ in parts):
            return None
        return math.sqrt(sum(v * v * n for v, n in parts) / sum(n for _, n in parts))

    @property
    def rms_before(self) -> float:
        """RMS position error [m] of the smooth model with the starting values."""
        return self._total("rms_before")

    @property
    def rms_after(self) -> float:
        """RMS position error [m] of the smooth model with the fitted values."""
        return self._total("rms_after")

    @property
    def rms_before_exact(self) -> float | None:
        return self._total("rms_before_exact")

    @property
    def rms_after_exact(self) -> float | None:
        """RMS position error [m] of the exact simulator with the fitted values."""
        return self._total("rms_after_exact")

    def per_recording_json(self) -> dict:
        """{recording name: {parameter: {"value", "stderr"}, "rms_before", "rms_after"}} of the
        parameters fitted per recording (``name@k``), with each recording's exact RMS [m]."""
        out = {}
        for k, seg in enumerate(self.segments):
            own = {
                n.split("@")[0]: e.to_json() for n, e in self.params.items() if n.endswith(f"@{k}")
            }
            if own:
                names = [s.name for s in self.segments]
                key = seg.name if names.count(seg.name) == 1 else f"{seg.name} #{k + 1}"
                out[key] = {
                    "parameters": own,
                    "rms_before": seg.rms_before_exact,
                    "rms_after": seg.rms_after_exact,
                }
        return out

    def plant(self, base: Plant | None = None) -> Plant:
        """The fitted plant for closed-loop use: ``base`` (default: :attr:`cart` where the fit
        made one, else the first closed- or open-loop recording's plant, else the handout's)
        with the fitted values."""
        if base is None and self.cart is not None:
            return self.cart
        if base is None:
            driven = [s.plant for s in self.segments if s.plant.motor_connected]
            base = driven[0] if driven else handout_plant()
        return with_values(base, replacements(base, self.values))

    def to_json(self) -> dict:
        """{"params": {name: {"value", "stderr"}}, "rms_before", "rms_after" [m], ...}: the
        RMS values are the exact simulator's where it ran, else the smooth model's."""
        exact = self.rms_after_exact is not None
        return {
            "params": {n: e.to_json() for n, e in self.params.items()},
            "rms_before": self.rms_before_exact if exact else self.rms_before,
            "rms_after": self.rms_after_exact if exact else self.rms_after,
            "rms_before_smooth": self.rms_before,
            "rms_after_smooth": self.rms_after,
            "n_data": self.n_data,
            "recordings": [
                {
                    "name": s.name,
                    "kind": s.kind,
                    "start_time": float(s.time[0]),
                    "stop_time": float(s.time[-1]),
                    "rms_before": s.rms_before_exact,
                    "rms_after": s.rms_after_exact,
                    "rms_before_smooth": s.rms_before,
                    "rms_after_smooth": s.rms_after,
                    "nuisance": {k: e.to_json() for k, e in s.nuisance.items()},
                }
                for s in self.segments
            ],
            "correlation": {f"{a},{b}": c for (a, b), c in self.correlation.items()},
            "values": dict(self.values),
            "seconds": self.seconds,
            "model_explains_data": not self.misfit,
            "noise_floor": self.noise_floor,
            "n_effective": self.n_effective,
            "optimizer": list(self.stages),
            "converged": self.converged,
            "held": {n: e.held_at for n, e in self.params.items() if not e.identifiable},
            "per_recording": self.per_recording_json(),
            "warnings": self.warnings,
        }


def _finite(x):
    """x as a float, or None where it is missing or not finite (JSON has no inf or nan)."""
    return float(x) if x is not None and math.isfinite(x) else None


def _rms(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else 0.0
