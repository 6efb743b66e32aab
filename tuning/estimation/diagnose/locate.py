"""Where the residual carries structure beyond the encoder's quantization, and what it
correlates with.

The residual r = y_model - y_measured of the baseline fit on the exact simulator is compared with
its floor, the encoder's sawtooth (q / sqrt(12) RMS). A moving RMS over 15 ms above three times
that floor marks a window (gaps under 30 ms merged, windows under 5 ms dropped). Each window gets
the loop's regime there (the majority over its samples) and its share of the residual's energy.

Residual tests (on the whole residual): whiteness (lag-1 autocorrelation and a Ljung-Box
statistic over 20 lags of the residual decimated to 10 ms), and correlations with the command,
with sign(velocity) and with position, each with a z value rho sqrt(n_eff). What each points to
is :func:`points_to`.
"""

from __future__ import annotations

import math

import numpy as np

from jaxcart.effects import REGISTRY
from jaxcart.params import ENCODER_RESOLUTION
from tuning.estimation.engine.noise import effective_samples

#: The parameter corrections a residual correlated with a signal can point to.
_CORRECTIONS = {"command": ("gain (gamma_scale)",), "acceleration": ("mass (M)",)}


def points_to() -> dict:
    """Which kinds of physics a residual correlated with each signal can explain: every effect
    that declares the signal (``Effect.shows_in``, the registry as it is now), then the
    corrections."""
    return {
        signal: tuple(n for n, cls in REGISTRY.items() if signal in cls.shows_in)
        + _CORRECTIONS.get(signal, ())
        for signal in ("command", "sign_velocity", "position", "acceleration")
    }


REGIMES = ("command at its limit", "reversing", "stuck", "accelerating", "settling", "coasting")


def moving_rms(x, n):
    n = max(1, int(n))
    c = np.concatenate([[0.0], np.cumsum(x * x)])
    half = n // 2
    k = np.arange(x.size)
    lo = np.clip(k - half, 0, x.size)
    hi = np.clip(k + half + 1, 0, x.size)
    return np.sqrt((c[hi] - c[lo]) / np.maximum(hi - lo, 1))


def smooth_velocity(y, ts, window=0.01):
    v = np.gradient(y, ts)
    w = max(3, int(round(window / ts)))
    kernel = np.ones(w) / w
    padded = np.concatenate([np.full(w, v[0]), v, np.full(w, v[-1])])
    return np.convolve(padded, kernel, mode="same")[w:-w]


def regimes(seg, command, v_limit):
    """Per-sample regime labels of one segment (indices into REGIMES, or -1: moving)."""
    y = seg.target
    ts = seg.experiment.sample_time
    n = y.size
    vel = smooth_velocity(y, ts)
    acc = smooth_velocity(vel, ts, 0.02)
    q = seg.quantization or ENCODER_RESOLUTION
    slow = np.abs(vel) < max(q / 0.02, 1e-4)
    label = np.full(n, -1)
    moving_dir = np.sign(vel) * (~slow)
    rev = np.zeros(n, dtype=bool)
    w = max(1, int(round(0.02 / ts)))
    for k in np.flatnonzero(np.diff(np.sign(vel)) != 0):
        if np.any(~slow[max(0, k - w) : k + w]):
            rev[max(0, k - w) : k + w] = True
    del moving_dir
    if seg.kind == "closed_loop":
        r = np.asarray(seg.experiment.signal, dtype=float)
        span = max(np.ptp(r), np.ptp(y), 1e-6)
        near = np.abs(r - y) < 0.05 * span
    else:
        near = np.zeros(n, dtype=bool)
    u = np.zeros(n) if command is None else np.asarray(command, dtype=float)
    driven = np.abs(u) > 0.05
    at_limit = np.isfinite(v_limit) & (np.abs(u) >= 0.98 * v_limit) if command is not None else 0
    big_acc = np.abs(acc) > 0.3
    order = [
        (REGIMES.index("coasting"), (~driven) & (~slow)),
        (REGIMES.index("settling"), near & (~big_acc)),
        (REGIMES.index("accelerating"), big_acc),
        (REGIMES.index("stuck"), slow & driven & ~near),
        (REGIMES.index("reversing"), rev),
        (REGIMES.index("command at its limit"), np.asarray(at_limit, dtype=bool)),
    ]
    for code, mask in order:  # later entries take precedence
        label[np.asarray(mask, dtype=bool)] = code
    return label, vel, acc


def windows(segments, residuals, commands, limits, floor):
    """Windows of structure in the residual: list of dicts (recording, start, end [s],
    regime, share of the residual's energy, rms)."""
    total = sum(float(r @ r) for r in residuals) or 1.0
    out = []
    for seg, r, u, lim in zip(segments, residuals, commands, limits, strict=True):
        ts = seg.experiment.sample_time
        t0 = seg.start * ts
        mr = moving_rms(r, round(0.015 / ts))
        above = mr > 3 * floor
        labels, _, _ = regimes(seg, u, lim)
        k = 0
        n = r.size
        spans = []
        while k < n:
            if not above[k]:
                k += 1
                continue
            j = k
            while j < n and above[j]:
                j += 1
            spans.append([k, j])
            k = j
        merged = []
        gap = round(0.03 / ts)
        for s in spans:
            if merged and s[0] - merged[-1][1] < gap:
                merged[-1][1] = s[1]
            else:
                merged.append(s)
        for a, b in merged:
            if (b - a) * ts < 0.005:
                continue
            lab = labels[a:b]
            known = lab[lab >= 0]
            regime = REGIMES[int(np.bincount(known).argmax())] if known.size else "moving"
            counts = {REGIMES[c]: int((lab == c).sum()) for c in set(known.tolist())}
            out.append(
                dict(
                    recording=seg.name,
                    start=round(t0 + a * ts, 4),
                    end=round(t0 + (b - 1) * ts, 4),
                    regime=regime,
                    regimes={k2: round(v / (b - a), 3) for k2, v in counts.items()},
                    share=round(float(r[a:b] @ r[a:b]) / total, 4),
                    rms=float(np.sqrt(np.mean(r[a:b] ** 2))),
                )
            )
    out.sort(key=lambda w: -w["share"])
    return out


def residual_tests(segments, residuals, commands, n_eff):
    """Whiteness and correlations of the residual with command, sign(velocity), position."""
    r_all, sig = [], {"command": [], "sign_velocity": [], "position": [], "acceleration": []}
    lag1 = []
    q_stats = []
    for seg, r, u in zip(segments, residuals, commands, strict=True):
        ts = seg.experiment.sample_time
        _, vel, acc = regimes(seg, u, math.inf)
        r_all.append(r)
        sig["command"].append(np.zeros_like(r) if u is None else np.asarray(u))
        sig["sign_velocity"].append(np.sign(vel) * (np.abs(vel) > 1e-4))
        sig["position"].append(seg.target - seg.target.mean())
        sig["acceleration"].append(acc)
        rc = r - r.mean()
        if rc @ rc > 0:
            lag1.append(float(rc[1:] @ rc[:-1] / (rc @ rc)))
        dec = r[:: max(1, round(0.01 / ts))]
        dec = dec - dec.mean()
        m = dec.size
        if m > 25 and dec @ dec > 0:
            acf = [float(dec[h:] @ dec[:-h] / (dec @ dec)) for h in range(1, 21)]
            q_stats.append(m * (m + 2) * sum(a * a / (m - h) for h, a in enumerate(acf, 1)))
    r = np.concatenate(r_all)
    out = {
        "whiteness": {
            "lag1_autocorrelation": round(float(np.mean(lag1)) if lag1 else 0.0, 4),
            "ljung_box_q20": round(float(np.sum(q_stats)), 1),
            "white": bool((np.sum(q_stats) if q_stats else 0.0) < 31.4 * max(len(q_stats), 1)),
        }
    }
    for name, parts in sig.items():
        x = np.concatenate(parts)
        x = x - x.mean()
        rc = r - r.mean()
        den = math.sqrt(float(x @ x) * float(rc @ rc))
        rho = float(x @ rc) / den if den > 0 else 0.0
        z = rho * math.sqrt(max(n_eff, 1))
        out[name] = {
            "correlation": round(rho, 4),
            "z": round(z, 2),
            "significant": bool(abs(z) > 3.0),
            "points_to": list(points_to()[name]),
        }
    return out


def describe_residual(residual, sample_time: float) -> str:
    """What is left in a residual [m], in words: white (no structure a model could take up),
    a slow drift, or a ripple at its dominant frequency, with the share of its energy there.

    White: its effective independent samples are most of its samples (the autocorrelation
    dies within a few samples). Otherwise the periodogram's largest peak above the lowest
    bins: below 1 Hz a drift, else a ripple at that frequency."""
    r = np.asarray(residual, dtype=float)
    r = r[np.isfinite(r)]
    if r.size < 16 or not np.any(r):
        return "nothing"
    if effective_samples([r - r.mean()]) > 0.5 * r.size:
        return "white noise"
    spec = np.abs(np.fft.rfft(r - r.mean())) ** 2
    freq = np.fft.rfftfreq(r.size, sample_time)
    k = int(np.argmax(spec[1:])) + 1
    share = float(spec[max(k - 1, 1) : k + 2].sum() / spec[1:].sum())
    if freq[k] < 1.0:
        return f"a slow drift (strongest at {freq[k]:.2g} Hz, {share:.0%} of its energy)"
    return f"a ripple at {freq[k]:.3g} Hz ({share:.0%} of its energy)"
