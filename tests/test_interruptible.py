"""Long commands stop at Ctrl-C within a second (tuning/commands/interruptible.py): the work
runs in a worker thread that Python's SIGINT handler cannot reach, the main thread waits in
0.1 s slices."""

import os
import signal
import subprocess
import sys

import pytest

from tuning.commands import interruptible


def test_result_and_exception_come_back():
    assert interruptible.run(lambda a, b: a + b, 2, 3) == 5
    with pytest.raises(ValueError, match="bad"):
        interruptible.run(lambda: (_ for _ in ()).throw(ValueError("bad")))


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_ctrl_c_ends_a_blocked_command(tmp_path):
    """The worker blocks for ever in a call that never returns to Python (as XLA does); a
    SIGINT ends the process with status 130 (its speed is the machine's: not asserted)."""
    # The child takes Python's own Ctrl-C handler and unblocks SIGINT whatever it inherited
    # from the test process, and says "ready" from the worker thread; the main thread may still
    # be starting it (Thread.start waits for it), and a SIGINT there ends it the same way.
    code = (
        "import signal, threading\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])\n"
        "from tuning.commands import interruptible\n"
        "def blocked():\n"
        "    print('ready', flush=True)\n"
        "    threading.Event().wait()\n"
        "interruptible.run(blocked)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline().strip() == "ready"
    os.kill(proc.pid, signal.SIGINT)
    try:  # the work never ends by itself: only the signal can end it (a hang guard, no timing)
        rc = proc.wait(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail(f"SIGINT did not end the command; its stderr: {err!r}")
    with proc.stdout, proc.stderr:
        err = proc.stderr.read()
    assert rc == 130, (rc, err)
    assert "interrupted" in err


def test_background_work_returns_its_result_or_raises_its_error_and_does_not_hold_exit():
    """jaxcart.background.Background (the lab's diagnosis beside its parts): result() waits
    and returns, an exception is raised where result() is called, the thread is a daemon."""
    import threading

    from jaxcart.background import Background

    gate = threading.Event()
    slow = Background(lambda: gate.wait(5) and 42)
    assert slow.alive() and slow._thread.daemon
    gate.set()
    assert slow.result() == 42 and not slow.alive()

    def fail():
        raise ValueError("recording p50.toml: no samples")

    with pytest.raises(ValueError, match="no samples"):
        Background(fail).result()
