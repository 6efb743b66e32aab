"""A Quanser HIL board (Q2-USB, Q8-USB, ...) through the ``quanser.hardware`` Python API.

The API ships with Quanser's SDK (not on PyPI), so it is imported only when a board starts.
The board's own clock paces the loop, as in Quanser's examples::

    card = HIL("q2_usb", "0")
    card.write_analog([0], 1, [0.0])                        # start from 0 V
    card.set_encoder_counts([0], 1, [0])                    # the position reads 0 here
    card.watchdog_set_analog_expiration_state([0], 1, [0.0]); card.watchdog_start(0.1)
    task = card.task_create_encoder_reader(buffer, [0], 1)
    card.task_start(task, Clock.HARDWARE_CLOCK_0, 1000.0, 2**31 - 1)
    every sample: card.task_read_encoder(task, 1, counts)   # blocks until the next tick
                  card.watchdog_reload(); card.write_analog([0], 1, [u])
    finally:      write 0 V, task_stop, task_delete, watchdog_stop, watchdog_clear, close

The watchdog sets the analog output to 0 V by itself if the loop stops reloading it (a hung
process, a process killed with SIGKILL, a read blocked in the driver), on boards that support
expiration states; on the others that is recorded and the loop's own watchdog and ``finally``
remain. ``watchdog_reload()`` answers False once the watchdog has expired: the loop then stops
with that reason (the board has already set 0 V; ``watchdog_clear`` in stop() re-enables the
outputs). Every ``HILError`` becomes a :class:`DeviceError`
with the board's message.
"""

from __future__ import annotations

import numpy as np

from hw.devices.base import DeviceError
from hw.devices.sim import ENCODER_RESOLUTION

#: Boards known to drive the IP02 (any HIL board name of the SDK is accepted).
BOARDS = ("q2_usb", "q8_usb", "qpid_e", "qpid", "q8", "q4")
#: Number of samples the encoder task buffers (the loop reads one at a time).
_BUFFER = 1000
#: Samples to run: "until stopped" (the examples' np.iinfo(np.int32).max).
_FOREVER = int(np.iinfo(np.int32).max)


def _load_api():
    try:
        # lazy: the vendor's API may be absent (hw/ imports numpy and the stdlib only)
        import quanser.hardware as api
    except ImportError:
        raise DeviceError(
            "the Quanser HIL Python API (quanser.hardware) is not installed: install it from "
            "Quanser's SDK (Quanser's Python packages, not on PyPI) on the lab PC, or run with "
            "--device sim"
        ) from None
    return api


class QuanserBoard:
    """One encoder channel in, one analog output channel out, on a Quanser HIL board.

    board: board type ("q2_usb", "q8_usb", ...); identifier: which board ("0");
    encoder_channel, analog_channel: channel numbers; metres_per_count: encoder scale [m]
    (sign -1 if the encoder counts the other way); watchdog: the board's watchdog timeout [s]
    (0: not armed); api: the ``quanser.hardware`` module, or a stand-in for tests.
    """

    hardware_timed = True
    virtual = False

    def __init__(
        self,
        board: str = "q2_usb",
        identifier: str = "0",
        *,
        encoder_channel: int = 0,
        analog_channel: int = 0,
        metres_per_count: float = ENCODER_RESOLUTION,
        watchdog: float = 0.1,
        api=None,
    ):
        self.name = board
        self.board, self.identifier = board, str(identifier)
        self.metres_per_count = float(metres_per_count)
        self.watchdog = float(watchdog)
        self._api = api
        self._enc = np.array([encoder_channel], dtype=np.uint32)
        self._ana = np.array([analog_channel], dtype=np.uint32)
        self._counts = np.zeros(1, dtype=np.int32)
        self._volts = np.zeros(1, dtype=np.float64)
        self.card = self.task = None
        self.watchdog_state = "off"
        self.last_voltage = 0.0
        self.stop_errors: list[str] = []

    def _error(self, what, exc) -> DeviceError:
        message = exc.get_error_message() if hasattr(exc, "get_error_message") else str(exc)
        return DeviceError(f"{self.board} {self.identifier}: {what}: {message}")

    def start(self, sample_time: float) -> None:
        api = self._api or _load_api()
        self._api = api
        hil_error = api.HILError
        try:
            self.card = api.HIL(self.board, self.identifier)
        except hil_error as exc:
            raise self._error("cannot open the board (is it plugged in and free?)", exc) from None
        try:
            self.write(0.0)
            self.card.set_encoder_counts(self._enc, 1, np.zeros(1, dtype=np.int32))
            if self.watchdog > 0:
                try:
                    self.card.watchdog_set_analog_expiration_state(self._ana, 1, np.zeros(1))
                    self.card.watchdog_start(self.watchdog)
                    self.watchdog_state = f"armed, {self.watchdog:g} s, analog -> 0 V"
                except hil_error as exc:
                    self.watchdog_state = f"not supported by the board ({self._error('', exc)})"
            self.task = self.card.task_create_encoder_reader(_BUFFER, self._enc, 1)
            self.card.task_start(
                self.task, api.Clock.HARDWARE_CLOCK_0, 1.0 / float(sample_time), _FOREVER
            )
        except hil_error as exc:
            self.stop()
            raise self._error("cannot start the encoder task", exc) from None

    def read(self) -> float:
        try:
            self.card.task_read_encoder(self.task, 1, self._counts)  # blocks until the tick
            expired = self.watchdog_state.startswith("armed") and (
                self.card.watchdog_reload() is False  # False: it had expired already
            )
        except self._api.HILError as exc:
            raise self._error("reading the encoder", exc) from None
        if expired:
            raise DeviceError(
                f"{self.board} {self.identifier}: the board's watchdog expired (the loop was "
                f"more than {self.watchdog:g} s late): the board had set the output to 0 V"
            )
        return float(self._counts[0]) * self.metres_per_count

    def write(self, volts: float) -> None:
        if self.card is None:
            return  # never opened (or closed): nothing is driven
        self._volts[0] = volts
        try:
            self.card.write_analog(self._ana, 1, self._volts)
        except self._api.HILError as exc:
            raise self._error("writing the analog output", exc) from None
        self.last_voltage = float(volts)

    def stop(self) -> None:
        """0 V out, then stop and close everything; each step runs whatever the others do."""
        if self.card is None:
            return
        card, hil_error = self.card, self._api.HILError
        steps = [("write 0 V", lambda: self.write(0.0))]
        if self.task is not None:
            task = self.task
            steps += [
                ("task_stop", lambda: card.task_stop(task)),
                ("task_delete", lambda: card.task_delete(task)),
            ]
        if self.watchdog_state.startswith("armed"):
            steps += [
                ("watchdog_stop", card.watchdog_stop),
                ("watchdog_clear", card.watchdog_clear),
                # Writes fail while the watchdog is expired; cleared, 0 V is written again.
                ("write 0 V after watchdog_clear", lambda: self.write(0.0)),
            ]
        steps.append(("close", card.close))
        for what, step in steps:
            try:
                step()
            except (hil_error, DeviceError) as exc:
                self.stop_errors.append(f"{what}: {exc}")
        self.card = self.task = None

    def describe(self) -> dict:
        return {
            "name": self.board,
            "identifier": self.identifier,
            "encoder_channel": int(self._enc[0]),
            "analog_channel": int(self._ana[0]),
            "metres_per_count": self.metres_per_count,
            "watchdog": self.watchdog_state,
            "clock": "HARDWARE_CLOCK_0",
        }
