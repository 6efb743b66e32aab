"""A device that plays a recording back: read() returns the recorded positions one by one.

What the loop writes is kept (``written``), so a replay with the gains that ran checks that the
loop computes the recorded voltages (column v) from the recorded positions. After the last
sample the position holds its last value.
"""

from __future__ import annotations

from pathlib import Path

from hw.devices.base import DeviceError
from hw.expfile import ExpFileError, read_experiment_data


class Replay:
    name = "replay"
    hardware_timed = False
    virtual = True

    def __init__(self, path):
        self.path = Path(path)
        try:
            self.data = read_experiment_data(self.path)
        except ExpFileError as exc:
            raise DeviceError(f"replay: {exc}") from None
        self._positions = [float(y) for y in self.data.position]
        self.last_voltage = 0.0
        self.written: list[float] = []

    @property
    def sample_time(self) -> float:
        return self.data.sample_time

    def start(self, sample_time: float) -> None:
        ts = self.data.sample_time
        if abs(sample_time - ts) > 1e-9 * ts:
            raise DeviceError(
                f"replay: {self.path} was recorded at {ts} s per sample, the controller runs at "
                f"{sample_time} s; replay it with gains of the same sample time"
            )
        self._k = 0
        self.written = []
        self.last_voltage = 0.0

    def read(self) -> float:
        y = self._positions[min(self._k, len(self._positions) - 1)]
        self._k += 1
        return y

    def write(self, volts: float) -> None:
        self.last_voltage = float(volts)
        self.written.append(self.last_voltage)

    def stop(self) -> None:
        self.last_voltage = 0.0

    def describe(self) -> dict:
        return {"name": self.name, "source": str(self.path), "samples": len(self._positions)}
