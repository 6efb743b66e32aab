"""The one small protocol every device of the loop speaks (the loop never knows which it drives).

    loop                         device
    ----                         ------
    start(sample_time)   ---->   zero the encoder, 0 V out, start the clock (if it has one)
    every sample k:
      read()             ---->   y_k [m]; a hardware-timed device blocks until sample k
      write(u_k)         ---->   u_k [V], held until the next write
    stop()               ---->   0 V out, outputs safe, closed (never raises; may run twice)

A device that can run without real time (a simulation, a replay) sets ``virtual = True``; the
loop then runs it as fast as the machine allows, with timestamps k Ts.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable


class DeviceError(RuntimeError):
    """A device that cannot start, read or write; the message says what to check."""


@runtime_checkable
class Device(Protocol):
    """A cart the loop can drive.

    name: what ran (recorded in [device] name)
    hardware_timed: read() blocks until the next sample of the device's own clock
    virtual: the device can run faster than real time (simulation, replay)
    last_voltage: the last voltage written [V] (0 before any write)
    """

    name: str
    hardware_timed: bool
    virtual: bool
    last_voltage: float

    def start(self, sample_time: float) -> None: ...

    def read(self) -> float: ...

    def write(self, volts: float) -> None: ...

    def stop(self) -> None: ...

    def describe(self) -> dict: ...
