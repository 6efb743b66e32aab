"""The noise a correct model leaves, and what the residual is worth: the encoder count, the
noise floor, the effective number of independent samples, and standard errors widened for
model error. ``jaxcart fit`` and ``jaxcart diagnose`` judge by these alone."""

from __future__ import annotations

import math

import numpy as np

#: A fit whose RMS error exceeds this many times the noise floor (:func:`noise_floor`) is
#: reported as a model that does not explain the data (the fits of correct models on encoder
#: data end at 1.0-1.3 times it).
MISFIT_RATIO = 3.0
#: Smallest noise floor [m]: a smooth model differs from the exact one by about this much.
FLOOR_MIN = 1e-6
#: The encoder floor of a joint fit's criterion (:class:`RecordingNoise`): RMS below
#: FLOOR_FACTOR * q / sqrt(12) explains nothing.
FLOOR_FACTOR = 1.5


def encoder_count(position) -> float:
    """The count size q [m] of encoder data (every value a whole number of counts), or 0.

    q is the smallest step between samples (or that refined on the steps, then on the
    positions), accepted when it is between 0.1 um and 1 mm, every position is the first one
    plus a whole multiple of it (to 1e-6 of a count, or the text's rounding: positions shifted
    by an offset, written to 9 digits, to fixed decimals or in single precision, are still
    counts), and the
    positions scatter from sample to sample by less than a count (white noise written to
    1 um is not an encoder of 1 um counts)."""
    y = np.asarray(position, dtype=float)
    steps = np.abs(np.diff(y))
    steps = steps[steps > 1e-12]
    if steps.size == 0 or not np.all(np.isfinite(y)):
        return 0.0
    q = float(steps.min())
    d = y - y[0]
    # A value written with 9 significant digits is off by up to half a unit of its 9th digit,
    # 5e-9 |y| where the digits start with 1 (0.169908620); a difference of two such values
    # by up to one unit of the largest one's 9th digit.
    ymax = float(np.max(np.abs(y)))
    slack = 10.0 ** (math.floor(math.log10(ymax)) - 8) if ymax > 0 else 0.0
    # Written to fixed decimals ("%.6f": 1 um), a difference is off by up to one unit of them.
    slack = max(slack, _decimal_unit(y))
    # Saved in single precision (a scope's float32 .mat), a value is off by up to half a unit of
    # its 24th bit (1.5e-8 m at 0.4 m: a thousandth of a count).
    if np.array_equal(y, y.astype(np.float32)) and ymax > 0:
        slack = max(slack, float(np.spacing(np.float32(ymax))))
    # White noise written to a resolution is not an encoder: its samples scatter by many
    # "counts" (an encoder's second differences are 0 or one count: the level 0.6 count at most).
    scatter = noise_level(y)
    # The smallest step; else q refined on the steps (the smallest one, a difference of two
    # rounded values, can be off by 1e-5 of a count written to 9 digits, by 3 % to 1 um); else
    # q refined on all the positions, counted from the first one.
    by_steps = _refined(steps, q)
    sizes = [q, by_steps, _refined(d, by_steps)]
    for size in sizes:
        off = np.abs(d / size - np.round(d / size)) if size > 0 else np.inf
        if 1e-7 <= size <= 1e-3 and np.max(off) < max(1e-6, slack / size):
            return size if scatter <= size else 0.0
    return 0.0


def _refined(values, size: float) -> float:
    """The count size that makes ``values`` [m] whole multiples of it, from ``size`` [m]: fitted
    on the values within 2 counts of 0, then 4 times farther each pass (a size good to a
    tenth of a count at 2 counts is good to a tenth at 8 once refitted on them)."""
    reach = 2.5
    while size > 0:
        near = np.abs(values) <= reach * size
        counts = np.round(values[near] / size)
        if np.any(counts):
            size = float(np.dot(counts, values[near]) / np.dot(counts, counts))
        if np.all(near):
            break
        reach *= 4.0
    return size


def _decimal_unit(y) -> float:
    """The unit of the last decimal the positions were written with (1e-6 for "%.6f"), or 0
    when they carry more than 12 decimals."""
    for places in range(1, 13):
        scaled = y * 10.0**places
        if np.max(np.abs(scaled - np.round(scaled))) < 1e-3:
            return 10.0**-places
    return 0.0


def noise_level(position) -> float:
    """Standard deviation [m] of white noise on positions, from the median absolute second
    difference (a smooth motion sampled at 1 ms barely contributes to it)."""
    d2 = np.diff(np.asarray(position, dtype=float), 2)
    if d2.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6))


def effective_samples(parts) -> float:
    """Effective number of independent residuals, summed over parts (arrays, one per segment):
    N / tau per part,
    tau = 1 + 2 sum rho_k the integrated autocorrelation time of the residual about zero (a
    bias counts as correlation), summed to the first lag where rho_k <= 0 (Geyer's cut-off).
    Encoder error held for hundreds of samples, or a smooth model error, make tau large."""
    total = 0.0
    for part in parts:
        part = np.asarray(part, dtype=float)
        n = part.size
        if n < 2 or not np.all(np.isfinite(part)) or not np.any(part):
            total += max(n, 1)
            continue
        spec = np.fft.rfft(part, 2 * n)
        acf = np.fft.irfft(spec * np.conj(spec))[:n]
        rho = acf / acf[0]
        neg = np.flatnonzero(rho[1:] <= 0)
        cut = int(neg[0]) + 1 if neg.size else n
        tau = max(1.0, 1.0 + 2.0 * float(np.sum(rho[1:cut])))
        total += n / tau
    return max(total, 1.0)


def misfits(rms: float, floor: float) -> bool:
    """True when an RMS error is model error rather than noise: above :data:`MISFIT_RATIO`
    times the noise floor (``jaxcart fit`` and ``jaxcart diagnose`` both judge by it)."""
    return rms > MISFIT_RATIO * floor


def widened_for_model_error(stderr, naive_variance, n: int, n_eff: float) -> np.ndarray:
    """Standard errors of a model that does not explain the data (:func:`misfits`).

    The residual is model error (or uninformative data), not noise: its ``n_eff`` independent
    samples (:func:`effective_samples`) support the naive sigma^2 (J^T J)^-1 times N / n_eff,
    which the sandwich can miss when the error is one slow wave; the larger of the two.
    stderr: the robust standard errors; naive_variance: the diagonal of sigma^2 (J^T J)^-1
    (sigma^2 = RSS / (N - p)), in the same units squared; n: residuals N."""
    tau = n / n_eff
    return np.maximum(stderr, np.sqrt(naive_variance * tau))


def floor_of(segments) -> float:
    """RMS position error [m] a correct model leaves on prepared ``segments``
    (:class:`~.segments.Segment`: positions ``target`` [m], encoder count ``quantization`` [m]
    or 0): the encoder's q / sqrt(12), or for data that are not whole counts their white noise
    (:func:`noise_level`); weighted by samples, at least :data:`FLOOR_MIN`. Shared by
    ``jaxcart fit`` and ``jaxcart diagnose``."""
    total = n = 0
    for seg in segments:
        positions, q = np.asarray(seg.target, dtype=float), seg.quantization
        # Encoder data are whole counts (their noise is in the counts); other data: white noise.
        var = q**2 / 12 if q > 0 else noise_level(positions) ** 2
        total += positions.size * var
        n += positions.size
    return max(math.sqrt(total / max(n, 1)), FLOOR_MIN)


def repeatability(runs) -> dict:
    """How far repeated runs of one experiment differ: what a real cart repeats, the floor
    below which no model of it can be judged.

    runs: {index: (key, positions [m])}, ``key`` equal for runs of the same experiment (kind,
    controller, reference, sample time). Returns {index: RMS [m]} for each run that has a
    repeat: the RMS distance of the runs of its group from their mean over their common
    length (for two runs, the RMS of their difference / 2)."""
    groups: dict = {}
    for i, (key, y) in runs.items():
        groups.setdefault(key, []).append((i, np.asarray(y, dtype=float)))
    out = {}
    for members in groups.values():
        if len(members) < 2:
            continue
        n = min(y.size for _, y in members)
        stack = np.stack([y[:n] for _, y in members])
        spread = stack - stack.mean(axis=0)
        level = float(np.sqrt(np.mean(spread**2)))
        for i, _ in members:
            out[i] = level
    return out


def count_runs(target, quantization: float) -> float:
    """Effective number of independent samples of one recording's positions [m]: for encoder
    data (count ``quantization`` [m] > 0) the number of runs of equal counts (a count held for
    hundreds of samples is one reading), else every sample; at most a third of the samples."""
    target = np.asarray(target, dtype=float)
    if quantization > 0:
        counts = np.floor(target / quantization)
        runs = 1 + int(np.count_nonzero(np.diff(counts)))
    else:
        runs = target.size
    return float(min(runs, target.size / 3))


class RecordingNoise:
    """What each recording of a joint fit is worth, and the criterion that weighs them.

    floors: each recording's criterion floor f_k [m] (``factor`` times its own noise floor,
    :func:`floor_of`: below it a residual explains nothing); n_eff: the effective samples nu
    each recording counts for, the same for each (the mean of their :func:`count_runs`);
    sizes: its samples N_k. Every recording has a noise level of its own (a tap fits to
    micrometres where a closed-loop run of the same cart misses by millimetres), so the
    criterion is the likelihood with one variance per recording,

        sum_k nu log(max(mse_k, f_k^2) / f_k^2),

    in which a recording's misfit counts relative to its own level, and every recording as
    much as another: one run fitted worse cannot buy a tap fitted ten times worse, and a long
    run that nothing explains (a PD run held back by something the model lacks, 6.7 s against
    the tap's 1.2 s of coasting) cannot outvote the others. A joint fit minimises it by least
    squares with the weights :meth:`weights` (iteratively reweighted)."""

    def __init__(self, segments, factor: float = FLOOR_FACTOR):
        self.floors = np.array([factor * floor_of([s]) for s in segments])
        runs = [max(count_runs(s.target, s.quantization), 1.0) for s in segments]
        self.n_eff = np.full(len(runs), float(np.mean(runs)))
        self.sizes = np.array([s.target.size for s in segments], dtype=float)

    @property
    def total(self) -> float:
        """Effective samples of every recording together (at least 10)."""
        return max(float(self.n_eff.sum()), 10.0)

    def misfit(self, residuals) -> float:
        """sum_k nu_k log(max(mse_k, f_k^2) / f_k^2) of the residuals [m], one array per
        recording (0 where every recording is within its floor)."""
        out = 0.0
        for r, f, nu in zip(residuals, self.floors, self.n_eff, strict=True):
            r = np.asarray(r, dtype=float)
            mse = float(np.mean(r * r)) if r.size else 0.0
            out += nu * math.log(max(mse, f * f) / (f * f)) if math.isfinite(mse) else math.inf
        return out

    def criterion(self, residuals) -> float:
        """sum_k nu_k log((mse_k + f_k^2) / f_k^2): :meth:`misfit` with its floor smoothed, the
        cost whose gradient :meth:`weights` are (``jaxcart fit``'s joint objective)."""
        mse = _mse(residuals)
        if not np.all(np.isfinite(mse)):
            return math.inf
        f2 = self.floors**2
        return float(np.sum(self.n_eff * np.log((mse + f2) / f2)))

    def sum_of_squares(self, residuals) -> float:
        """The weighted sum of squares sum_k nu_k mse_k / (mse_k + f_k^2) whose change is the
        :meth:`criterion`'s to first order (the weights of :meth:`weights` before their
        normalisation)."""
        mse = _mse(residuals)
        return float(np.sum(self.n_eff * mse / (mse + self.floors**2)))

    def weights(self, residuals) -> np.ndarray:
        """Each recording's weight for its squared residuals in a joint least-squares fit at
        ``residuals`` [m] (one array each): nu_k / (N_k (mse_k + f_k^2)) [1/m^2], the gradient
        of :meth:`misfit` (with its floor smoothed); one recording's are all equal."""
        mse = _mse(residuals)
        mse = np.where(np.isfinite(mse), mse, np.inf)
        w = self.n_eff / (self.sizes * (mse + self.floors**2))
        return w / np.max(w) if np.max(w) > 0 else np.ones_like(w)


def _mse(residuals) -> np.ndarray:
    """The mean square [m^2] of each recording's residuals (one array each)."""
    return np.array([float(np.mean(np.asarray(r, dtype=float) ** 2)) for r in residuals])
