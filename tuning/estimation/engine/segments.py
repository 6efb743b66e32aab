"""Parts of a recording worth fitting: a tap's coasting part and a run's start state."""

from __future__ import annotations

import numpy as np

from jaxcart.params import ENCODER_RESOLUTION


def coasting_segment(
    position, sample_time: float, *, margin: float = 0.02, quantization: float = ENCODER_RESOLUTION
) -> tuple[int, int]:
    """The coasting part of a tap recording as sample indices (start, stop).

    start: ``margin`` [s] after the peak speed (the end of the push: the hand's force is gone
    once the cart outruns it); stop: the first sample from which the cart makes no further
    progress in its direction for 50 ms (rest), plus the samples it then stays within one count
    of rest (at most 50 ms; a real cart may then drift back). Raises UserError without motion.
    """
    y = np.asarray(position, dtype=float)
    n = y.size
    w = max(3, int(round(0.01 / sample_time)))  # 10 ms moving average of the velocity
    v = np.gradient(y, sample_time)
    kernel = np.ones(w) / w
    padded = np.concatenate([np.full(w, v[0]), v, np.full(w, v[-1])])
    v_smooth = np.convolve(padded, kernel, mode="same")[w:-w]
    peak = int(np.argmax(np.abs(v_smooth)))
    count = quantization if quantization > 0 else 1e-6
    if abs(v_smooth[peak]) * 0.05 < 3 * count:  # under 3 counts in 50 ms: no tap
        raise ValueError("no tap found: the cart never moves more than a few encoder counts")
    direction = np.sign(v_smooth[peak])
    start = min(peak + int(round(margin / sample_time)), n - 2)
    z = direction * y
    window = max(2, int(round(0.05 / sample_time)))
    # Running maximum of what is still to come: rest where nothing ahead exceeds the present.
    ahead = np.maximum.accumulate(z[::-1])[::-1]
    stop = n - 1
    for k in range(start, n - 1):
        if ahead[min(k + 1, n - 1)] <= z[k] and np.all(z[k : k + window] <= z[k]):
            stop = k
            break
    end = stop
    while end + 1 < n and end - stop < window and abs(y[end + 1] - y[stop]) <= 1.01 * count:
        end += 1
    return start, end + 1


def initial_state(time, y, start):
    """(y0, yd0) at sample ``start`` from a quadratic over the next 20 ms [m, m/s]."""
    k = min(y.size - start, max(5, int(round(0.02 / (time[1] - time[0]))) + 1))
    t = time[start : start + k] - time[start]
    coef = np.polyfit(t, y[start : start + k], 2 if k > 5 else 1)
    return float(np.polyval(coef, 0.0)), float(np.polyval(np.polyder(coef), 0.0))
