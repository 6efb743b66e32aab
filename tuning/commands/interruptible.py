"""Long commands that stop at Ctrl-C within a second.

A fit or a diagnosis spends most of its time inside compiled XLA programs, where Python's
SIGINT handler does not run until the program returns (a 10-million-sample fit ignored Ctrl-C
for over a minute). Such a command runs in a worker thread; the main thread waits in short
slices, so Ctrl-C reaches it at once. The worker cannot be stopped inside XLA, so the process
then exits without waiting for it: outputs are written atomically (hw.atomicio), so nothing
half-written is left under a user's name.
"""

from __future__ import annotations

import os
import sys

from jaxcart.background import Background

#: How often the waiting main thread looks up [s].
SLICE = 0.1


def run(func, *args):
    """``func(*args)`` in a worker thread; its result, or its exception re-raised here. A
    KeyboardInterrupt while waiting ends the process at once with status 130."""
    try:  # the start too: Thread.start waits for the worker, which may already be running
        worker = Background(func, *args, name="jaxcart-command")
        while worker.alive():
            worker.join(SLICE)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(130)
    return worker.result()
