"""The cart as measured: a fitted cart, how far each of its values can be trusted, and carts
drawn from it.

A fit gives each value of the cart with a standard error (and, where the fit knows them, the
correlations between them); a drive that does not repeat itself gives each driven run its own
limit (``v_sat@k``), whose spread from run to run is what the next run may have.
:func:`from_fit` collects both from a :class:`tuning.estimation.fit.FitResult` (the lab's joint
fit, or a diagnosis's through :attr:`tuning.estimation.diagnose.result.Diagnosis.fit`), and
:meth:`CartUncertainty.draw` draws carts from it:

- the shared values (B_eq, f_c, delay, ...) from the normal distribution of the fit: mean the
  fitted values, covariance from the standard errors and correlations (a fit that gives
  standard errors alone: independent), each standard error at least the spread of the value
  over the fits that left one recording out (:func:`held_out_spread`, the jackknife's: where
  the recordings disagree, the model leaves something out or its noise is not white, and the
  standard errors understate);
- each drive value (a limit free per run) as a new run's: the mean of the runs' values plus
  their standard deviation times sqrt(1 + 1/n) times Student's t with n - 1 degrees of
  freedom (a new run about n runs whose mean and spread are both estimated: the predictive
  distribution of a normal sample), and the standard error of the mean of their fits. A
  normal draw of that scale held a new run's value in its 90 % band 63 % of the time from
  two runs and 74 % from three (in theory 66 and 76 %; ``test_prediction``); the t, 88-90 %;
- every value clipped into the range a cart of this lab has (the parameter's plausible range,
  :attr:`jaxcart.effects.Param.fit_range`).

>>> import jaxcart as jc
>>> u = CartUncertainty(jc.build_plant({"B_eq": 1.5, "f_c": 0.4}), ("B_eq", "f_c"),
...                     np.array([1.5, 0.4]), np.diag([0.02, 0.01]) ** 2)
>>> [sorted(v) for v in u.draw(2, seed=0)]
[['B_eq', 'f_c'], ['B_eq', 'f_c']]
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from jaxcart import plantspec
from jaxcart.params import Plant
from jaxcart.plantspec import build_plant

#: A drive value of one run is the same parameter as the shared one: ``v_sat@2`` is ``v_sat``.
PER_RUN_MARK = "@"


@dataclass(frozen=True, eq=False)
class CartUncertainty:
    """A fitted cart with the uncertainty of its values.

    plant: the fitted cart (every effect, the sensor included; each drive value at the
    median of the runs); names: the shared values that vary; mean: their fitted values [SI];
    cov: their covariance [SI^2] (positive semidefinite); drive: {name: the driven runs' own
    values [SI]} of each value free per run; drive_stderr: {name: the standard errors of
    those values [SI]}; source: where the fit comes from, in words; widened: {name: (the
    fit's standard error, the held-out spread) [SI]} of each shared value whose standard error
    is the spread of the fits that left one recording out (:func:`held_out_spread`)."""

    plant: Plant
    names: tuple
    mean: np.ndarray
    cov: np.ndarray
    drive: dict = field(default_factory=dict)
    drive_stderr: dict = field(default_factory=dict)
    source: str = "a fit"
    widened: dict = field(default_factory=dict)

    @property
    def varied(self) -> tuple:
        """Every value a drawn cart varies: the shared ones, then the drive's."""
        return tuple(self.names) + tuple(self.drive)

    def stderr(self, name: str) -> float:
        """How far ``name`` may be from the fitted cart's value for the next run [SI]: its
        standard error (a shared value) or the scale of a new run's spread (a drive value,
        :meth:`drive_spread`: the t's scale with the standard error of the mean beside it, not
        a standard deviation, which two runs leave infinite)."""
        if name in self.drive:
            return self.drive_spread(name)[1]
        i = self.names.index(name)
        return math.sqrt(max(float(self.cov[i, i]), 0.0))

    def drive_spread(self, name: str) -> tuple[float, float]:
        """(mean, scale) of a new run's value of the drive value ``name`` [SI]: the runs'
        mean; their spread times sqrt(1 + 1/n) (the scale of the t a new run is drawn from,
        :meth:`drive_parts`), with the standard error of that mean from the runs' own fits."""
        mean, spread, se_mean = self.drive_parts(name)[:3]
        return mean, math.hypot(spread, se_mean)

    def drive_parts(self, name: str) -> tuple[float, float, float, int]:
        """(mean, scale of the runs' spread, standard error of the mean, degrees of freedom)
        of a new run's value of ``name`` [SI]: mean + spread t_dof + se_mean z (the module
        docstring); dof = n - 1 (0 and no spread from one run)."""
        runs = np.asarray(self.drive[name], dtype=float)
        n = runs.size
        spread = float(np.std(runs, ddof=1)) * math.sqrt(1.0 + 1.0 / n) if n > 1 else 0.0
        se = np.asarray(self.drive_stderr.get(name, np.zeros(n)), dtype=float)
        se_mean = float(np.sqrt(np.sum(se**2))) / n if n else 0.0
        return float(np.mean(runs)), spread, se_mean, max(n - 1, 0)

    def nominal(self) -> dict:
        """The fitted cart's varied values [SI] (the drive's at its mean over the runs)."""
        out = dict(zip(self.names, (float(x) for x in self.mean), strict=True))
        out.update({n: self.drive_spread(n)[0] for n in self.drive})
        return out

    def nominal_cart(self) -> Plant:
        """The fitted cart at :meth:`nominal`'s values (each drive value at its runs' mean)."""
        return self.cart(self.nominal())

    def draw(self, n: int, *, seed: int = 0, tails: bool = True) -> list[dict]:
        """``n`` carts' values ({name: value [SI]}), drawn as the module docstring says;
        ``tails`` False: each drive value from the normal distribution of the t's scale (the
        tuner's training carts, :func:`tuning.design.for_cart.training_carts`)."""
        rng = np.random.default_rng(seed)
        k = len(self.names)
        shared = np.zeros((n, 0))
        if k:
            root = _sqrt_psd(self.cov)
            shared = self.mean[None, :] + rng.standard_normal((n, k)) @ root.T
        out = [dict(zip(self.names, (float(x) for x in row), strict=True)) for row in shared]
        for name in self.drive:
            mean, spread, se_mean, dof = self.drive_parts(name)
            if tails and dof:
                x = mean + spread * rng.standard_t(dof, n) + se_mean * rng.standard_normal(n)
            else:
                x = mean + math.hypot(spread, se_mean) * rng.standard_normal(n)
            for values, v in zip(out, x, strict=True):
                values[name] = float(v)
        return [{name: clipped(name, v) for name, v in values.items()} for values in out]

    def cart(self, values: dict) -> Plant:
        """The fitted cart with ``values`` ({name: value [SI]}) in place of its own."""
        return build_plant(values, base=self.plant, check=False, where="a drawn cart")

    def scaled(self, factor: float) -> CartUncertainty:
        """The same cart with every standard error and spread ``factor`` times as wide."""
        drive = {
            n: np.mean(v) + factor * (np.asarray(v, float) - np.mean(v))
            for n, v in self.drive.items()
        }
        stderr = {n: factor * np.asarray(v, float) for n, v in self.drive_stderr.items()}
        return dataclasses.replace(self, cov=self.cov * factor**2, drive=drive, drive_stderr=stderr)


def clipped(name: str, value: float) -> float:
    """``value`` [SI] held inside the range a cart of this lab has for ``name``."""
    lo, hi = plantspec.param(name).fit_range
    return float(min(max(value, lo), hi))


def _sqrt_psd(cov: np.ndarray) -> np.ndarray:
    """A matrix R with R R^T = cov (cov symmetric positive semidefinite; negative rounding
    in its eigenvalues taken as 0)."""
    w, v = np.linalg.eigh((cov + cov.T) / 2)
    return v * np.sqrt(np.clip(w, 0.0, None))[None, :]


def from_fit(fit, *, plant: Plant | None = None, source: str = "the joint fit") -> CartUncertainty:
    """The uncertainty of a :class:`tuning.estimation.fit.FitResult` ``fit``: its shared values
    with standard errors (and correlations where the fit has them), and the values free per
    run as the drive's run-to-run spread; ``plant``: the fitted cart (default ``fit.plant()``).
    A value without a standard error (held, or not determined) stays at the fitted cart's; one
    whose fits without each recording spread further than its standard error says takes that
    spread (:func:`held_out_spread`), its correlations kept."""
    plant = fit.plant() if plant is None else plant
    shared, drive, drive_se = {}, {}, {}
    for name, est in fit.params.items():
        if est.value is None or "[" in name:  # (a vector's values are not drawn)
            continue
        base, mark, _ = name.partition(PER_RUN_MARK)
        if mark:
            drive.setdefault(base, []).append(float(est.value))
            se = est.stderr if est.stderr is not None and math.isfinite(est.stderr) else 0.0
            drive_se.setdefault(base, []).append(float(se))
        elif est.stderr is not None and math.isfinite(est.stderr) and est.stderr > 0:
            shared[name] = (float(est.value), float(est.stderr))
    names = tuple(shared)
    mean = np.array([shared[n][0] for n in names])
    se = np.array([shared[n][1] for n in names])
    corr = np.eye(len(names))
    for (a, b), rho in (getattr(fit, "correlation", None) or {}).items():
        if a in names and b in names and math.isfinite(rho):
            i, j = names.index(a), names.index(b)
            corr[i, j] = corr[j, i] = float(rho)
    spread = held_out_spread(names, getattr(fit, "segments", ()))
    wide = {n: (float(a), float(b)) for n, a, b in zip(names, se, spread, strict=True) if b > a}
    se = np.maximum(se, spread)
    return CartUncertainty(
        plant,
        names,
        mean,
        corr * np.outer(se, se),
        {n: tuple(v) for n, v in drive.items()},
        {n: tuple(v) for n, v in drive_se.items()},
        source,
        wide,
    )


#: Fewer recordings held out than this say nothing of the spread (0 then).
MIN_HELD_OUT = 3


def held_out_spread(names, segments) -> np.ndarray:
    """The jackknife standard error [SI] of each shared value ``names`` over the fits that left
    one recording out (each segment's :attr:`~tuning.estimation.fitting.result.SegmentFit.held_out`,
    the n of them that have one): sqrt((n - 1) / n * sum (x_i - mean)^2). A correct model's
    values move with a recording left out about as its standard errors say; a model that
    leaves something out fits each subset differently (on the independent cart with a 1.2 A
    current limit and a 5.8 V amplifier limit, the current limit alone fitted: 1.204 A
    without the P 50 step, 1.232-1.234 A without any other run, a spread of 0.023 A against a
    standard error of 0.003 A). 0 for a value with fewer than :data:`MIN_HELD_OUT` folds."""
    folds = [s.held_out for s in segments if getattr(s, "held_out", None)]
    out = np.zeros(len(names))
    for i, n in enumerate(names):
        x = np.array([f[n] for f in folds if n in f], dtype=float)
        if x.size >= MIN_HELD_OUT:
            out[i] = math.sqrt((x.size - 1) / x.size * float(np.sum((x - x.mean()) ** 2)))
    return out


def fit_table(u: CartUncertainty) -> dict:
    """The uncertainty as a plant file's [fit] entries (:func:`from_fit_table` reads them):
    ``stderr`` {name: [SI]} of the shared values and, for the drive, ``runs`` {name: each
    run's value} and ``runs_stderr`` {name: their standard errors}."""
    out = {"stderr": {n: u.stderr(n) for n in u.names}}
    if u.drive:
        out["runs"] = {n: [float(x) for x in v] for n, v in u.drive.items()}
        out["runs_stderr"] = {n: [float(x) for x in v] for n, v in u.drive_stderr.items()}
    return out


def from_fit_table(
    plant: Plant, fit: dict, *, source: str = "a plant file"
) -> CartUncertainty | None:
    """The uncertainty a plant file's [fit] table holds (``stderr``, as ``jaxcart fit --out``
    and ``jaxcart lab``'s ``cart_plant.toml`` write it; ``runs`` and ``runs_stderr`` for a
    drive free per run), about ``plant``'s own values; None where it gives no standard
    error."""
    stderr = {
        n: float(se)
        for n, se in (fit.get("stderr") or {}).items()
        if n in plant.param_names() and isinstance(se, int | float) and math.isfinite(se) and se > 0
    }
    runs = {n: tuple(float(x) for x in v) for n, v in (fit.get("runs") or {}).items() if v}
    if not stderr and not runs:
        return None
    names = tuple(n for n in stderr if n not in runs)
    runs_se = {n: tuple(float(x) for x in v) for n, v in (fit.get("runs_stderr") or {}).items()}
    return CartUncertainty(
        plant,
        names,
        np.array([float(plant.get(n)) for n in names]),
        np.diag([stderr[n] ** 2 for n in names]),
        runs,
        {n: runs_se.get(n, (0.0,) * len(v)) for n, v in runs.items()},
        source,
    )
