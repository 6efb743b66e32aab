"""Devices of the hardware loop, behind one protocol (:mod:`hw.devices.base`): the simulated
cart, a Quanser HIL board, and a replay of a recording."""

from hw.devices.base import Device, DeviceError
from hw.devices.quanser import BOARDS, QuanserBoard
from hw.devices.replay import Replay
from hw.devices.sim import CartParams, SimCart, load_cart_params

__all__ = [
    "BOARDS",
    "CartParams",
    "Device",
    "DeviceError",
    "QuanserBoard",
    "Replay",
    "SimCart",
    "load_cart_params",
]
