"""A clock the tests drive (:class:`hw.pacing.Timer`), so that what the hardware loop does with
time is tested without depending on the load of the machine that runs the tests."""

from __future__ import annotations

from hw.devices.sim import CartParams, SimCart
from hw.pacing import Timer

#: Each reading of the clock moves it on by this much [s] (so a spin on it ends).
TICK = 1e-6


class FakeClock:
    """Time [s] that moves only when told: ``sleep(s)`` and ``stall(s)`` move it by s, each
    reading by :data:`TICK`, and :meth:`at_sample` to sample k of a hardware-timed task."""

    def __init__(self, start: float = 1000.0):
        self.t = start
        self.task_start: float | None = None
        self.sample_time = 0.001

    def now(self) -> float:
        self.t += TICK
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += max(float(seconds), 0.0)

    def stall(self, seconds: float) -> None:
        """Something (a busy machine, a slow driver) holds the loop for ``seconds``."""
        self.t += seconds

    def start_task(self, sample_time: float) -> None:
        """A hardware-timed task starts now, one sample every ``sample_time`` [s]."""
        self.task_start, self.sample_time = self.t, sample_time

    def at_sample(self, k: int) -> None:
        """A hardware-timed read of sample k (0 first) returns at its tick, or at once when
        that tick has passed (the board's clock never waits for a late loop)."""
        self.t = max(self.t, self.task_start + k * self.sample_time)

    @property
    def timer(self) -> Timer:
        return Timer(now=self.now, sleep=self.sleep)


class Stalling(SimCart):
    """The simulated cart whose read number ``at`` (0 first) holds the loop ``seconds`` on
    ``clock`` (a machine too busy for real time, at a moment the test chooses)."""

    def __init__(self, clock: FakeClock, at: int, seconds: float, **params):
        super().__init__(CartParams(**params))
        self.clock, self.at, self.seconds, self.reads = clock, at, seconds, 0

    def read(self):
        if self.reads == self.at:
            self.clock.stall(self.seconds)
        self.reads += 1
        return super().read()
