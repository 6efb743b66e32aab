"""Devices: the Quanser adapter against a fake HIL (every call recorded, the encoder backed by
the simulated cart), its fault paths, the replay device, and the simulated cart's options."""

import math
import types

import numpy as np
import pytest
from fakeclock import FakeClock

from hw.control_law import PID
from hw.devices.base import Device, DeviceError
from hw.devices.quanser import QuanserBoard
from hw.devices.replay import Replay
from hw.devices.sim import ENCODER_RESOLUTION, CartParams, SimCart, load_cart_params
from hw.loop import run_loop
from jaxcart.files import read_experiment

PID_LAB = PID(kp=40.0, kd=5.0, ki=5.0, v_limit=6.0)


class HILError(Exception):
    def __init__(self, code, message):
        super().__init__(message)
        self.error_code, self.message = code, message

    def get_error_message(self):
        return self.message


def fake_api(
    cart=None, *, watchdog=True, fail=None, fail_at=None, expire_at=None, hook=None, clock=None
):
    """A stand-in for ``quanser.hardware``; ``api.calls`` lists every call (name, args);
    ``api.clock`` (:class:`fakeclock.FakeClock`) is the board's clock, each encoder read at
    its sample's tick, for the loop's ``timer=api.clock.timer``."""
    calls = []
    cart = cart or SimCart(CartParams(quantization=0.0))
    clock = clock or FakeClock()

    class HIL:
        def __init__(self, board, identifier):
            calls.append(("HIL", board, identifier))
            if fail == "open":
                raise HILError(-1, "no board")
            self.reads = 0

        def __getattr__(self, name):
            def call(*args):
                calls.append((name, *[a.tolist() if hasattr(a, "tolist") else a for a in args]))
                if name == fail and (fail_at is None or self.reads >= fail_at):
                    raise HILError(-2, f"{name} failed")
                if name == "watchdog_set_analog_expiration_state" and not watchdog:
                    raise HILError(-3, "not supported")
                if name == "write_analog":
                    cart.write(float(args[2][0]))
                if name == "task_read_encoder":
                    clock.at_sample(self.reads)
                    self.reads += 1
                    if hook is not None:
                        hook(self.reads)
                    args[2][0] = math.floor(cart.read() / ENCODER_RESOLUTION)
                if name == "task_create_encoder_reader":
                    return "task-1"
                if name == "task_start":
                    cart.start(1.0 / args[2])
                    clock.start_task(1.0 / args[2])
                if name == "watchdog_reload":
                    return expire_at is None or self.reads < expire_at  # False: expired
                return None

            return call

    api = types.SimpleNamespace(
        HIL=HIL,
        HILError=HILError,
        Clock=types.SimpleNamespace(HARDWARE_CLOCK_0="HW0"),
        calls=calls,
        cart=cart,
        clock=clock,
    )
    return api


def _names(api):
    return [c[0] for c in api.calls]


def test_board_runs_the_loop_like_the_simulated_cart(tmp_path):
    api = fake_api()
    board = QuanserBoard("q2_usb", "0", api=api)
    assert isinstance(board, Device)
    result = run_loop(
        board, PID_LAB, np.full(1001, 0.3), out=tmp_path / "q2.toml", timer=api.clock.timer
    )
    assert result.status == "completed", result.fault
    direct = run_loop(SimCart(), PID_LAB, np.full(1001, 0.3), clock="virtual")
    np.testing.assert_allclose(result.position, direct.position, rtol=0, atol=1e-12)
    names = _names(api)
    # Opened, 0 V first, encoder zeroed, watchdog armed to 0 V, hardware clock at 1 kHz.
    assert api.calls[0] == ("HIL", "q2_usb", "0")
    assert api.calls[1] == ("write_analog", [0], 1, [0.0])
    assert api.calls[2] == ("set_encoder_counts", [0], 1, [0])
    assert api.calls[3] == ("watchdog_set_analog_expiration_state", [0], 1, [0.0])
    assert api.calls[4] == ("watchdog_start", 0.1)
    assert names[5] == "task_create_encoder_reader"
    assert api.calls[6] == ("task_start", "task-1", "HW0", 1000.0, 2**31 - 1)
    assert names.count("task_read_encoder") == 1001 and names.count("watchdog_reload") == 1001
    # On the way out: 0 V, then the task, the watchdog and the board closed.
    tail = names[names.index("task_stop") - 1 :]
    assert tail == [
        "write_analog",
        "task_stop",
        "task_delete",
        "watchdog_stop",
        "watchdog_clear",
        "write_analog",  # 0 V again: writes fail while an expired watchdog is not cleared
        "close",
    ]
    assert api.calls[names.index("task_stop") - 1] == ("write_analog", [0], 1, [0.0])
    rec = read_experiment(result.path)
    assert rec.meta["device"]["name"] == "q2_usb" and rec.meta["device"]["clock"] == "device"
    assert rec.meta["device"]["watchdog"].startswith("armed")


def _last_write(api):
    writes = [c for c in api.calls if c[0] == "write_analog"]
    return writes[-1][3][0] if writes else None


@pytest.mark.parametrize(
    "fail, fail_at, words",
    [
        ("open", None, "cannot open the board"),
        ("task_start", None, "cannot start the encoder task"),
        ("task_read_encoder", 200, "reading the encoder: task_read_encoder failed"),
    ],
)
def test_board_errors_stop_with_zero_volts(tmp_path, fail, fail_at, words):
    api = fake_api(fail=fail, fail_at=fail_at)
    board = QuanserBoard("q8_usb", "1", api=api)
    result = run_loop(
        board, PID_LAB, np.full(1001, 0.3), out=tmp_path / "e.toml", timer=api.clock.timer
    )
    assert result.status == "fault" and words in result.fault and "q8_usb 1" in result.fault
    if fail != "open":
        assert _last_write(api) == 0.0 and _names(api)[-1] == "close"
    assert board.card is None and board.last_voltage == 0.0
    meta = read_experiment(result.path).meta if result.n_samples >= 2 else None
    if meta:
        assert meta["run"]["fault"] == result.fault


def test_an_expired_board_watchdog_stops_the_run(tmp_path):
    """watchdog_reload() answers False once the board's watchdog expired (it set 0 V itself):
    the loop stops with that reason, and 0 V is written again once the watchdog is cleared."""
    api = fake_api(expire_at=300)
    board = QuanserBoard("q2_usb", "0", api=api)
    result = run_loop(
        board, PID_LAB, np.full(1001, 0.3), out=tmp_path / "w.toml", timer=api.clock.timer
    )
    assert result.status == "fault" and "watchdog expired" in result.fault
    assert result.n_samples == 299
    names = _names(api)
    assert names[-3:] == ["watchdog_clear", "write_analog", "close"] and _last_write(api) == 0.0
    assert read_experiment(result.path).meta["run"]["fault"] == result.fault


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP", "SIGINT"])
def test_a_signal_during_a_board_run_leaves_the_board_safe(tmp_path, name):
    """A signal while the board's encoder task runs: 0 V, then the task, the watchdog and the
    board closed, in that order, and the recording names the signal."""
    import signal

    def hook(reads):
        if reads == 250:
            signal.raise_signal(getattr(signal, name))

    api = fake_api(hook=hook)
    board = QuanserBoard("q2_usb", "0", api=api)
    result = run_loop(
        board, PID_LAB, np.full(1001, 0.3), out=tmp_path / "s.toml", timer=api.clock.timer
    )
    assert result.status == "fault" and result.signals == (name,)
    names = _names(api)
    tail = names[names.index("task_stop") - 1 :]
    assert tail[0] == "write_analog" and _last_write(api) == 0.0 and tail[-1] == "close"
    assert {"task_delete", "watchdog_stop", "watchdog_clear"} <= set(tail)
    meta = read_experiment(result.path).meta
    assert ({"SIGINT": "Ctrl-C"}.get(name, name)) in meta["run"]["fault"]
    assert meta["run"]["samples"] == 249


def test_board_without_watchdog_states_still_runs():
    api = fake_api(watchdog=False)
    board = QuanserBoard("q2_usb", "0", api=api)
    result = run_loop(board, PID_LAB, np.full(50, 0.1), timer=api.clock.timer)
    assert result.status == "completed"
    assert "not supported" in result.device["watchdog"]
    assert "watchdog_reload" not in _names(api) and "watchdog_stop" not in _names(api)


@pytest.mark.parametrize("stall, status", [(0.006, "fault"), (0.004, "completed")])
def test_a_late_read_on_the_boards_clock_trips_the_loops_watchdog(stall, status):
    """The board's clock is the loop's: a 6 ms stall before read 300 (the 5 ms watchdog)
    stops the run on that sample with 0 V; 4 ms passes. Timed by the fake clock, not the
    machine's load."""
    clock = FakeClock()
    api = fake_api(clock=clock, hook=lambda reads: reads == 300 and clock.stall(stall))
    board = QuanserBoard("q2_usb", "0", api=api)
    result = run_loop(board, PID_LAB, np.full(1001, 0.3), timer=clock.timer)
    assert result.status == status, result.fault
    if status == "fault":
        assert "watchdog: sample 299 (t = 0.299 s) was read 6 ms late" in result.fault
        assert result.n_samples == 300 and _last_write(api) == 0.0
    else:
        assert result.timing["late_max_us"] == pytest.approx(4000, abs=10)


def test_board_without_the_sdk_says_what_to_install():
    import sys

    if "quanser" in sys.modules:
        pytest.skip("the Quanser SDK is installed here")
    result = run_loop(QuanserBoard(), PID_LAB, np.full(50, 0.1))
    assert result.status == "fault" and "quanser.hardware" in result.fault


def test_replay_plays_a_recording_back_and_the_loop_recomputes_its_voltages(tmp_path):
    first = run_loop(
        SimCart(CartParams(f_c=0.3)),
        PID_LAB,
        np.full(801, 0.3),
        clock="virtual",
        out=tmp_path / "a",
    )
    replay = Replay(first.path)
    again = run_loop(replay, PID_LAB, first.reference, clock="virtual")
    np.testing.assert_array_equal(again.position, first.position)
    np.testing.assert_array_equal(again.command, first.command)
    with pytest.raises(DeviceError, match="recorded at 0.001 s"):
        Replay(first.path).start(0.002)


def test_sim_delay_saturation_and_parameters_file(tmp_path):
    # A delay of 2 samples: the first 2 samples of the drive are 0 V.
    cart = SimCart(CartParams(delay=0.002, quantization=0.0))
    cart.start(0.001)
    ys = [cart.read()]
    for _ in range(4):
        cart.write(6.0)
        ys.append(cart.read())
    assert ys[1] == 0.0 and ys[2] == 0.0 and ys[3] > 0.0
    with pytest.raises(DeviceError, match="whole number of samples"):
        SimCart(CartParams(delay=0.0015)).start(0.001)
    # Saturation: 12 V acts as v_sat = 3 V.
    a, b = SimCart(CartParams(v_sat=3.0, quantization=0)), SimCart(CartParams(quantization=0))
    for cart, volts in ((a, 12.0), (b, 3.0)):
        cart.start(0.001)
        cart.read()
        cart.write(volts)
    assert a.read() == b.read() > 0
    # Coulomb friction holds the cart below breakaway (0.3 N > 0.1 V * 1.72 N/V).
    c = SimCart(CartParams(f_c=0.3, quantization=0.0))
    c.start(0.001)
    c.read()
    c.write(0.1)
    assert c.read() == 0.0
    path = tmp_path / "cart.toml"
    path.write_text("B_eq = 4.6\nf_c = 0.45\ndelay = 0.001\n")
    p = load_cart_params(path)
    assert (p.B_eq, p.f_c, p.delay, p.M) == (4.6, 0.45, 0.001, 0.94)
    path.write_text("Beq = 4.6\n")
    with pytest.raises(DeviceError, match="unknown parameter 'Beq'"):
        load_cart_params(path)
    # In other units (g/s, grams): refused as jaxcart's plant refuses them, one range table.
    wrong = (("B_eq = 4600\n", "B_eq = 4600: out of its range"), ("M = 940\n", "M = 940"))
    for text, words in wrong:
        path.write_text(text)
        with pytest.raises(DeviceError, match=words):
            load_cart_params(path)
    # A plant file's values outside its [plant] table were dropped without a word.
    path.write_text('format = "jaxcart-plant"\nversion = 1\nB_eq = 4.6\n')
    with pytest.raises(DeviceError, match="unknown key 'B_eq'.*\\[plant\\] table"):
        load_cart_params(path)
    # The handout's constants (appendix): m = 1.0731 kg, B_emf = 7.7236 kg/s, gamma = 1.7235.
    p = CartParams()
    assert (round(p.m, 4), round(p.B_emf, 4), round(p.gamma, 4)) == (1.0731, 7.7236, 1.7235)


def test_sim_cart_reads_a_plant_file(tmp_path):
    """The simulated cart takes the plant file that fit and diagnose write: its effects are in
    the cart, effects it does not name are absent, effects it cannot model are refused."""
    import jaxcart as jc
    from hw.devices.base import DeviceError
    from hw.devices.sim import load_cart_params

    path = jc.write_plant_file(
        tmp_path / "p.toml", jc.build_plant({"B_eq": 3.0, "f_c": 0.3, "delay": 0.002})
    )
    params = load_cart_params(path)
    assert (params.B_eq, params.f_c, params.delay) == (3.0, 0.3, 0.002)
    assert params.v_sat == float("inf") and params.quantization == 0.0
    spring = jc.write_plant_file(tmp_path / "s.toml", jc.build_plant({"k_s": 5.0}))
    with pytest.raises(DeviceError, match="does not model spring"):
        load_cart_params(spring)
