"""``python -m hw``: see :mod:`hw.cli`."""

import signal
import sys

from hw.cli import main

status = main(exiting=True)
# A signal after the run (a fourth Ctrl-C) is ignored to the end: the run is stopped and
# recorded, and Python would otherwise die of it while it exits.
for _name in ("SIGINT", "SIGTERM", "SIGHUP"):
    if hasattr(signal, _name):
        signal.signal(getattr(signal, _name), signal.SIG_IGN)
sys.exit(status)
