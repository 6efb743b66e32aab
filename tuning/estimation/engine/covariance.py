"""The parameter covariances every fit of the engine reports: robust and naive, with the
directions the data do not determine flagged.

Robust: the sandwich B^-1 S B^-1 (B = J^T J). Per recording the samples are grouped into runs
within one encoder count of the model's position (:func:`runs`): the encoder's error is
nearly constant within a run and nearly independent between runs. S is the larger (in the
positive-semidefinite sense) of

- S_data: the Newey-West long-run covariance of the runs' CR3-adjusted scores
  (:func:`cluster_scores`), which sees noise, quantization and model error in the residuals,
  and whose lags absorb smooth model error;
- S_encoder: sum over runs of (q^2 / 12) g_b g_b^T, g_b the run's column sums of J: the
  encoder's own share, known from the count q [m]; the residual of a run that the fit pulls
  towards itself (a cart at rest, one run of hundreds of samples) underestimates it.

Naive: sigma^2 B^-1 with sigma^2 = RSS / (N - p). Both in the units of J's columns (a fit's
internal parameters); a caller converts to natural units with the value slopes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from tuning.estimation.engine import parameters
from tuning.estimation.engine.noise import effective_samples, widened_for_model_error


@dataclass
class Covariance:
    """Parameter covariances of one fit (``jaxcart fit``'s and ``jaxcart diagnose``'s), natural
    units (or a fit's internal ones, :func:`covariance`): ``robust`` (the engine's run-clustered
    sandwich with the encoder floor, :func:`tuning.estimation.engine.covariance.covariances`),
    ``naive`` (sigma^2 (J^T J)^-1, sigma^2 = RSS / (N - p)); a parameter the data do not
    determine has inf in its row and column; ``n`` residuals worth ``n_eff`` independent ones
    (:func:`tuning.estimation.engine.noise.effective_samples`); ``widened``: the residual is
    model error, and every standard error is widened as ``jaxcart fit`` widens its own
    (:func:`tuning.estimation.engine.noise.widened_for_model_error`)."""

    names: list
    robust: np.ndarray
    naive: np.ndarray
    n: int
    n_eff: float
    widened: bool

    def stderr(self, weights: dict) -> float:
        """Standard error of sum(weights[name] * name): one parameter ({name: 1}) or a
        difference ({"f_s": 1, "f_c": -1}); nan where one of them is not determined."""
        if any(n not in self.names for n in weights):
            return math.nan
        # Only the named entries: 0 * inf of an undetermined other one would be nan.
        i = [self.names.index(n) for n in weights]
        a = np.array(list(weights.values()), dtype=float)
        robust = self.robust[np.ix_(i, i)]
        if not np.all(np.isfinite(robust)):
            return math.nan
        var = float(a @ robust @ a)
        se = math.sqrt(max(var, 0.0))
        if self.widened:
            naive = max(float(a @ self.naive[np.ix_(i, i)] @ a), 0.0)
            se = float(widened_for_model_error(se, naive, self.n, self.n_eff))
        return se

    def stderrs(self) -> np.ndarray:
        """The standard error of every entry (inf where the data do not determine it), widened
        as :meth:`stderr` widens one."""
        se = np.sqrt(np.diag(self.robust))
        if self.widened:
            se = widened_for_model_error(se, np.diag(self.naive), self.n, self.n_eff)
        return se

    @property
    def singular(self) -> np.ndarray:
        """True for each entry the data do not determine (its variance not finite)."""
        return ~np.isfinite(np.diag(self.robust))


def bartlett_bandwidth(scores) -> int:
    """Andrews (1991) AR(1) plug-in bandwidth for the Bartlett kernel (scores: (n, p)); 0 for
    fewer than 3 scores (a recording whose model stays within one encoder count is one run:
    one score, no autocorrelation to estimate)."""
    n = scores.shape[0]
    if n < 3:
        return 0
    num = den = 0.0
    for x in scores.T:
        if not np.any(x):
            continue
        rho = float(np.dot(x[1:], x[:-1]) / max(np.dot(x[:-1], x[:-1]), 1e-300))
        rho = min(max(rho, -0.97), 0.97)
        s2 = float(np.mean((x[1:] - rho * x[:-1]) ** 2))
        num += 4 * rho**2 * s2**2 / ((1 - rho) ** 6 * (1 + rho) ** 2)
        den += s2**2 / (1 - rho) ** 4
    if den == 0:
        return 0
    alpha = num / den
    return int(min(n - 1, max(0, math.ceil(1.1447 * (alpha * n) ** (1 / 3)))))


def runs(model, quantization) -> np.ndarray:
    """Start indices of the runs of samples whose model position [m] stays within one encoder
    count (``quantization`` [m]) of the run's first sample (every sample its own run when
    quantization is 0)."""
    model = np.asarray(model, dtype=float)
    if not quantization > 0:
        return np.arange(model.size)
    starts = [0]
    ref = model[0]
    for k in range(1, model.size):
        if abs(model[k] - ref) >= quantization:
            starts.append(k)
            ref = model[k]
    return np.asarray(starts)


def cluster_scores(jac, r, starts, b_inv_sqrt, power=-0.5):
    """Scores J_b^T r~_b of the runs b (see :func:`runs`).

    Within a run the encoder's error is one count's sawtooth, strongly correlated, so a run is
    one observation. r~_b = (I - H_bb)^power r_b (-1/2: Bell-McCaffrey CR2; -1: CR3, the
    cluster jackknife) undoes the shrinking of a run's residuals by the fit itself (a run of
    400 samples at rest pulls the fit towards it); computed from the p x p matrices
    A_b = J_b^T J_b only."""
    s = np.add.reduceat(jac * r[:, None], starts, axis=0)  # (runs, p): J_b^T r_b
    a = np.add.reduceat(jac[:, :, None] * jac[:, None, :], starts, axis=0)  # (runs, p, p)
    # Leverage of each run: eigen-decomposition of B^-1/2 A_b B^-1/2 (eigenvalues in [0, 1)).
    lev = b_inv_sqrt @ a @ b_inv_sqrt
    lam, w = np.linalg.eigh(lev)
    lam = np.clip(lam, 0.0, 0.999)
    small = lam < 1e-8
    d = np.where(small, -power, ((1 - lam) ** power - 1) / np.where(small, 1.0, lam))
    # (I - H_bb)^power = I + U W D W^T U^T with U = J_b B^-1/2:
    # J_b^T r~_b = s_b + A_b B^-1/2 W D W^T B^-1/2 s_b.
    v = np.einsum("ij,bj->bi", b_inv_sqrt, s)
    v = np.einsum("bji,bj->bi", w, v) * d
    v = np.einsum("bij,bj->bi", w, v)
    v = np.einsum("ij,bj->bi", b_inv_sqrt, v)
    return s + np.einsum("bij,bj->bi", a, v)


def long_run(scores) -> np.ndarray:
    """Newey-West S = sum_{|l| <= L} (1 - |l|/(L+1)) Gamma_l of a series of scores."""
    lag = bartlett_bandwidth(scores)
    s = scores.T @ scores
    for k in range(1, lag + 1):
        g = scores[k:].T @ scores[:-k]
        s += (1 - k / (lag + 1)) * (g + g.T)
    return s


def _inverse(jac):
    """(column scales, scaled J, B^-1, B^-1/2, singular flags) of J: columns scaled to unit
    norm (the parameters' units differ by orders of magnitude), B = J^T J inverted on the
    directions the data determine."""
    # Each column's norm from the column over its largest entry: squares of a column of 1e200
    # (a run that blew up at a trial value) overflow, and eigh of the inf fails.
    peak = np.max(np.abs(jac), axis=0, initial=0.0)
    peak = np.where(peak > 0, peak, 1.0)
    norms = peak * np.linalg.norm(jac / peak, axis=0)
    zero = norms <= 1e-12 * max(float(norms.max(initial=0.0)), 1e-300)
    scale = np.where(zero, 1.0, norms)
    js = jac / scale
    w, v = np.linalg.eigh(js.T @ js)
    tiny = w <= 1e-13 * max(float(w.max(initial=0.0)), 1e-300)
    inv_w = np.where(tiny, 0.0, 1.0 / np.where(tiny, 1.0, w))
    singular = zero | np.any(np.abs(v[:, tiny]) > 1e-3, axis=1)
    return scale, js, (v * inv_w) @ v.T, (v * np.sqrt(inv_w)) @ v.T, singular


def determined(jac) -> bool:
    """Whether the data determine every parameter of J (no column zero or in the span of
    others)."""
    jac = np.asarray(jac, dtype=float)
    return bool(np.all(np.isfinite(jac))) and not np.any(_inverse(jac)[-1])


def covariances(jac, residuals, models, quantizations, weights=None, names=None) -> Covariance:
    """Robust and naive covariances (module docstring) of the parameters of J, in the units
    of J's columns (rows and columns of a parameter the data do not determine are inf).

    jac: (N, p) d residual / d parameter [m per unit], rows in the order of ``residuals``;
    residuals: one array [m] per recording; models: the model's positions [m] per recording
    (they decide the runs); quantizations: each recording's encoder count [m] (0: none);
    weights: each recording's weight in a weighted fit (its rows of J and its residuals scaled
    by the square root, and its encoder share with it), None for equal weights; names: of J's
    columns (default their indices)."""
    jac = np.asarray(jac, dtype=float)
    parts = [np.asarray(x, dtype=float) for x in residuals]
    weights = np.ones(len(parts)) if weights is None else np.asarray(weights, dtype=float)
    roots = np.sqrt(weights)
    jac = (
        jac
        * np.concatenate([np.full(x.size, w) for x, w in zip(parts, roots, strict=True)])[:, None]
    )
    parts = [x * w for x, w in zip(parts, roots, strict=True)]
    r = np.concatenate(parts) if parts else np.zeros(0)
    p = jac.shape[1]
    names = list(range(p)) if names is None else list(names)
    if p == 0:
        return Covariance(names, np.zeros((0, 0)), np.zeros((0, 0)), r.size, float(r.size), False)
    scale, js, b_inv, b_inv_sqrt, singular = _inverse(jac)
    s_data = np.zeros((p, p))
    s_enc = np.zeros((p, p))
    rows = np.split(js, np.cumsum([x.size for x in parts])[:-1], axis=0)
    for part_j, part_r, model, q, w in zip(
        rows, parts, models, quantizations, weights, strict=True
    ):
        starts = runs(model, q)
        s_data += long_run(cluster_scores(part_j, part_r, starts, b_inv_sqrt, power=-1.0))
        g = np.add.reduceat(part_j, starts, axis=0)
        s_enc += g.T @ g * w * q**2 / 12
    ev, vec = np.linalg.eigh(s_enc - s_data)
    meat = s_data + (vec * np.maximum(ev, 0.0)) @ vec.T
    unscale = np.outer(scale, scale)
    robust = b_inv @ meat @ b_inv / unscale
    naive = b_inv * float(r @ r) / max(r.size - p, 1) / unscale
    for cov in (robust, naive):
        cov[singular, :] = np.inf
        cov[:, singular] = np.inf
    return Covariance(names, robust, naive, r.size, float(r.size), False)


def covariance(
    segments, names, values, jac, residuals, widen_above=None, weights=None
) -> Covariance:
    """Robust and naive covariances in natural units (the engine's,
    :func:`tuning.estimation.engine.covariance.covariances`, of the fitted parameters: J per
    unit of each one's logarithm for a log-fitted one; runs by the model's positions, the
    residuals plus the targets); with an RMS residual above ``widen_above`` [m] the standard
    errors are widened for model error
    (:func:`tuning.estimation.engine.noise.widened_for_model_error`; :func:`diagnose` passes
    the criterion's floor, FLOOR_FACTOR times q / sqrt(12): what the criterion counts as
    structure to explain is not the encoder's own error); ``weights``: each recording's in a
    weighted joint fit. ``values`` None: in the units of J's columns (``jaxcart fit``'s
    internal coordinates)."""
    jac = np.asarray(jac, dtype=float)
    r = np.concatenate(residuals)
    p = len(names)
    jac = jac[:, :p]
    nan = np.full((p, p), np.nan)
    with np.errstate(over="ignore", invalid="ignore"):
        finite = np.all(np.isfinite(jac)) and np.all(np.isfinite(r))
        finite = finite and np.all(np.isfinite(jac.T @ jac))
    if not finite:  # a smooth fit that ran away: no standard errors
        return Covariance(list(names), nan, nan, r.size, 1.0, False)
    models = [np.asarray(x) + seg.target for x, seg in zip(residuals, segments, strict=True)]
    quantizations = [seg.quantization for seg in segments]
    cov = covariances(jac, residuals, models, quantizations, weights, names)
    # d value / d theta (log parameters); None: the internal units themselves.
    dv = (
        np.ones(p)
        if values is None
        else np.array([parameters.value_slope(n, values[n]) for n in names])
    )
    d = np.outer(dv, dv)
    rms = float(np.sqrt(np.mean(r * r))) if r.size else 0.0
    widened = widen_above is not None and rms > widen_above
    n_eff = effective_samples(residuals) if widened else float(r.size)
    return dataclasses.replace(
        cov, robust=cov.robust * d, naive=cov.naive * d, n_eff=n_eff, widened=widened
    )
