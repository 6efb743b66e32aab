"""The one XLA setting jaxcart's command line asks for before JAX starts a backend: loops as
whole kernels on a CPU. Importing this module imports no jax, and importing jaxcart changes no
setting: :func:`request` does, when called.

XLA:CPU runs a while loop (every ``lax.scan`` over the samples of a run) as a sequence of
tasks, one per fused operation per iteration. For a chunk of a few hundred runs the dispatch
of those tasks costs more than their arithmetic, and a wide chunk that amortizes it streams
the loop's state through the L2 cache at every sample. A loop whose one iteration touches
fewer bytes than the option ``xla_cpu_small_while_loop_byte_threshold`` is instead compiled
into one kernel, its state in the L1 cache. XLA's default is 1 kB, which none of ours meets;
:data:`LOOP_KERNEL_BYTES` admits the loops of chunks of a few hundred runs (W1: 256 runs per
chunk), of the tuner's starts and of the fits' batches, and leaves wide loops (thousands of
runs, forward-mode tangents) to the task runtime, where they run faster (measured, 2 cores:
W1 1.3x per CPU-second with 256-run chunks against 4096-run chunks without it; the bench's
gradient row 1.8x slower when its 4096-run loop is made one kernel).

The command line calls :func:`request` on the user's behalf once a command runs, before it
starts JAX (``tuning/commands/main.py``; a script asks the same by calling it before its first
JAX computation): it adds the option to ``XLA_FLAGS`` unless a JAX backend has already
started, so that it could not take effect, or the variable already sets it (the user's value is
kept: ``1024`` restores XLA's default), or ``JAXCART_XLA_FLAGS=0`` is set. The setting is the
process's (and its children's, which inherit the variable): it also applies to the process's
other JAX programs, whose loops of less than 1 MiB per iteration then compile whole too (wider
ones are left as they are). :func:`loop_kernels` says whether this process compiles loops
whole, and the batches choose their chunks from it. The
option is read by XLA's CPU compiler only (other backends leave ``xla_``-prefixed extra options
alone). Results are the same up to the rounding of the compiled arithmetic.
"""

from __future__ import annotations

import os
import re
import sys

#: The per-iteration bytes below which XLA:CPU compiles a while loop into one kernel.
LOOP_KERNEL_BYTES = 1 << 20
OPTION = "xla_cpu_small_while_loop_byte_threshold"
#: The environment variable that, set to 0, leaves XLA_FLAGS alone.
OFF = "JAXCART_XLA_FLAGS"
_EXTRA = "--xla_backend_extra_options="

#: The threshold in effect for this process: None until :func:`request` ran, 0 when the option
#: could not take effect (a backend started first) or was turned off.
_IN_EFFECT: int | None = None


def _backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        # lazy: jax costs 0.3 s at start-up (python -X importtime); the parser imports this module
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # another JAX: assume the worst
        return True


def _extra_options(flags: str) -> list:
    """Every ``--xla_backend_extra_options`` in ``flags`` (matches; the value is group 1). XLA
    merges them into one map (measured: an option in the first stays in effect beside a
    second), a key given twice taking its last value."""
    return list(re.finditer(rf"(?:^|\s){re.escape(_EXTRA)}(\S*)", flags))


def threshold_in(flags: str) -> int | None:
    """The value ``flags`` (an XLA_FLAGS string) gives :data:`OPTION`, else None (its last
    value over every ``--xla_backend_extra_options``)."""
    found = [
        v for m in _extra_options(flags) for v in re.findall(rf"(?:^|,){OPTION}=(\d+)", m.group(1))
    ]
    return int(found[-1]) if found else None


def with_option(flags: str, value: int = LOOP_KERNEL_BYTES) -> str:
    """``flags`` with :data:`OPTION` set to ``value`` unless it sets it already; added to the
    last ``--xla_backend_extra_options`` where there is one (an empty one included)."""
    if threshold_in(flags) is not None:
        return flags
    entry = f"{OPTION}={value}"
    matches = _extra_options(flags)
    if not matches:
        return f"{flags} {_EXTRA}{entry}".strip()
    last = matches[-1]
    merged = f"{last.group(1)},{entry}" if last.group(1) else entry
    return flags[: last.start(1)] + merged + flags[last.end(1) :]


def request() -> int:
    """Ask XLA to compile loops whole (see the module docstring); returns the threshold in
    effect [bytes], 0 when it could not be set (a backend had started already) or is turned
    off (:data:`OFF`). Idempotent."""
    global _IN_EFFECT
    if _IN_EFFECT is None:
        flags = os.environ.get("XLA_FLAGS", "")
        if os.environ.get(OFF, "").strip() == "0" or _backend_started():
            # Left alone; a user's own setting from the process's start is in effect all the same.
            _IN_EFFECT = threshold_in(flags) or 0
        else:
            os.environ["XLA_FLAGS"] = with_option(flags)
            _IN_EFFECT = threshold_in(os.environ["XLA_FLAGS"]) or 0
    return _IN_EFFECT


def loop_kernels() -> bool:
    """True when this process's CPU backend compiles jaxcart's chunked loops whole: after
    :func:`request`, or with the option set that high in the user's own ``XLA_FLAGS``."""
    if _IN_EFFECT is not None:
        return _IN_EFFECT >= LOOP_KERNEL_BYTES
    return (threshold_in(os.environ.get("XLA_FLAGS", "")) or 0) >= LOOP_KERNEL_BYTES
