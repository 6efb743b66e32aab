"""Real time, measured honestly: the timing summary of a run, its verdict, and the watchdog.

A loop on absolute deadlines k Ts that falls behind (a paused process, a busy machine) reads
the samples it missed back-to-back to catch up: its median period then reads tens of
microseconds, or exactly Ts, while samples were read milliseconds late. So the verdict is
judged on the lateness t_wall - k Ts of every sample, not on the periods:

    kept          no sample was read more than Ts/2 after its deadline
    fell behind   some were: how many, the latest, and the catch-up periods (< Ts/2)

The loop's watchdog stops a run whose sample is read more than ``late_max`` after its
deadline. Its default is chosen for the machine: a short probe of the same sleep-and-spin
pacing measures how late this machine wakes up under its present load, and the watchdog is
``WATCHDOG_MARGIN`` times that, at least ``WATCHDOG_MIN`` and at most ``WATCHDOG_MAX``.

The loop reads the time through a :class:`Timer` (the computer's: ``time.perf_counter`` and
``time.sleep``), which a caller may replace: the tests drive one of their own, so that what the
loop does with time (pacing, lateness, the watchdog) is checked without depending on the load
of the machine that runs them; real-time behaviour itself is measured (``python -m hw bench``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: The last stretch before a deadline is spun, not slept (sleep overshoots by ~50-100 us).
SPIN = 300e-6
#: A sample read later than this fraction of Ts after its deadline missed its slot.
BEHIND_FRACTION = 0.5
#: The watchdog's floor [s]: below it, ordinary scheduling noise would stop runs.
WATCHDOG_MIN = 0.005
#: The watchdog's ceiling [s]: at the cart's top speed (gamma 6 V / c = 0.8 m/s) it moves
#: at most 4 cm on a stale voltage before the run stops.
WATCHDOG_MAX = 0.05
#: The watchdog is this many times the worst lateness of the probe.
WATCHDOG_MARGIN = 5.0
#: Length of the probe [s].
PROBE_SECONDS = 0.2


@dataclass(frozen=True)
class Timer:
    """Where the loop reads the time and waits: ``now()`` [s, any origin], ``sleep(seconds)``."""

    now: Callable[[], float] = time.perf_counter
    sleep: Callable[[float], None] = time.sleep


#: The computer's clock: what every run uses unless given another timer.
SYSTEM_TIMER = Timer()


def wait_until(deadline: float, timer: Timer = SYSTEM_TIMER) -> None:
    """Sleep until shortly before ``deadline`` [s, on ``timer``], then spin the last stretch
    (sleep overshoots by ~50-100 us; the spin does not)."""
    now = timer.now
    remaining = deadline - now()
    if remaining > SPIN:
        timer.sleep(remaining - SPIN)
    while now() < deadline:
        pass


def timing_stats(t_wall, compute, sample_time: float, *, virtual: bool = False) -> dict:
    """Sample-period, lateness and compute-time statistics of a run ([timing]).

    Times in microseconds. period: steps of t_wall; late: t_wall - k Ts; overruns: samples
    whose write ended after the next deadline (per 10,000 samples too); late_samples: read
    more than Ts/2 late; catch_up_periods: periods under Ts/2 (the loop catching up);
    real_time: "kept" or "fell behind". In virtual time only the compute times mean anything.
    """
    n = int(np.size(t_wall))
    stats: dict = {"samples": n, "sample_time_us": sample_time * 1e6}
    if n == 0:
        return stats
    us = 1e6
    compute = np.asarray(compute, dtype=float)
    stats["compute_median_us"] = float(np.median(compute)) * us
    stats["compute_p99_us"] = float(np.percentile(compute, 99)) * us
    stats["compute_max_us"] = float(np.max(compute)) * us
    if virtual:
        stats["real_time"] = "virtual time (no pacing)"
    if virtual or n < 2:
        return _rounded(stats)
    t_wall = np.asarray(t_wall, dtype=float)
    period = np.diff(t_wall)
    late = t_wall - np.arange(n) * sample_time
    over = int(np.count_nonzero(t_wall + compute > (np.arange(n) + 1) * sample_time))
    behind = int(np.count_nonzero(late > BEHIND_FRACTION * sample_time))
    catch_up = int(np.count_nonzero(period < BEHIND_FRACTION * sample_time))
    stats.update(
        period_median_us=float(np.median(period)) * us,
        period_p99_us=float(np.percentile(period, 99)) * us,
        period_max_us=float(np.max(period)) * us,
        period_min_us=float(np.min(period)) * us,
        late_max_us=float(np.max(late)) * us,
        late_p99_us=float(np.percentile(late, 99)) * us,
        overruns=over,
        overruns_per_10000=over * 10000.0 / n,
        late_samples=behind,
        catch_up_periods=catch_up,
        real_time="kept" if behind == 0 else "fell behind",
    )
    return _rounded(stats)


def _rounded(stats: dict) -> dict:
    return {
        k: (round(v, 3) if isinstance(v, float) and math.isfinite(v) else v)
        for k, v in stats.items()
    }


def verdict(timing: dict) -> str:
    """One line on the pacing of a run, from its [timing] (never a healthy median alone)."""
    if "period_median_us" not in timing:
        return timing.get("real_time", "no timing")
    ts = timing["sample_time_us"]
    n = timing["samples"]
    median = timing["period_median_us"]
    if timing.get("late_samples", 0) == 0:
        return (
            f"real time kept: every sample read within {BEHIND_FRACTION * ts:.0f} us of its "
            f"deadline (latest {timing['late_max_us']:.0f} us); period median {median:.1f} us, "
            f"p99 {timing['period_p99_us']:.1f} us, max {timing['period_max_us']:.1f} us"
        )
    return (
        f"real time NOT kept: {timing['late_samples']} of {n} samples read more than "
        f"{BEHIND_FRACTION * ts:.0f} us late (latest {timing['late_max_us'] / 1e3:.3g} ms), "
        f"{timing['catch_up_periods']} back-to-back periods as the loop caught up; the median "
        f"period ({median:.1f} us) does not describe this run: close other programs, or run "
        "the simulated cart in virtual time"
    )


def probe_lateness(
    sample_time: float, seconds: float = PROBE_SECONDS, timer: Timer = SYSTEM_TIMER
) -> float:
    """The worst lateness [s] of this machine's sleep-and-spin pacing over ``seconds``."""
    n = max(10, int(round(seconds / sample_time)))
    t0 = timer.now() + 2 * SPIN
    worst = 0.0
    for k in range(n):
        deadline = t0 + k * sample_time
        wait_until(deadline, timer)
        worst = max(worst, timer.now() - deadline)
    return worst


def choose_watchdog(sample_time: float, probe=probe_lateness) -> tuple[float, str]:
    """The watchdog [s] for this machine, and a line saying how it was chosen (and, when the
    machine is too busy for it, how to choose another with ``--watchdog``)."""
    worst = float(probe(sample_time))
    chosen = min(max(WATCHDOG_MARGIN * worst, WATCHDOG_MIN), WATCHDOG_MAX)
    how = (
        f"watchdog {chosen * 1e3:.3g} ms: {WATCHDOG_MARGIN:g} x the worst wake-up "
        f"({worst * 1e3:.3g} ms) of a {PROBE_SECONDS:g} s probe of this machine, within "
        f"[{WATCHDOG_MIN * 1e3:g}, {WATCHDOG_MAX * 1e3:g}] ms"
    )
    if WATCHDOG_MARGIN * worst > WATCHDOG_MAX:
        how += (
            f"; this machine is too busy for real time now (woke up {worst * 1e3:.3g} ms "
            "late): close other programs, or give --watchdog S (a sample read S seconds late "
            f"stops the run; at {WATCHDOG_MAX:g} s the cart moves at most 4 cm on a stale "
            "voltage)"
        )
    return chosen, how
