"""What the tuner says: the verdict on its result, the note on a gain at its bound, and the
progress line while it iterates."""

from __future__ import annotations

import math
import sys

from tuning.design.losses import Spec


def verdict(meets, failing, info, spec: Spec, robust, n_plants) -> str:
    """One line: the specification met (where, with the metrics), or each constraint that
    fails and the best found."""
    where = f"on all {n_plants} plants of the set (worst case)" if robust else "exact simulator"
    got = f"settling {info.settling_time:.3f} s, overshoot {info.overshoot:.2f} %"
    if meets:
        return (
            f"meets the specification ({where}): {got} "
            f"(bounds {spec.settling_time:g} s, {spec.overshoot:g} %)"
        )
    parts = []
    for name in failing:
        if name == "settling_time":
            parts.append(
                f"settling time {info.settling_time:.3f} s is not under {spec.settling_time:g} s"
            )
        elif name == "overshoot":
            parts.append(f"overshoot {info.overshoot:.2f} % is not under {spec.overshoot:g} %")
        else:
            parts.append("the loop diverges")
    return f"cannot meet the specification ({where}): " + "; ".join(parts) + f". Best found: {got}"


def bound_note(gains, on_bound: dict, bounds: dict, widen: str | None = None) -> str | None:
    """One line naming every free parameter on (or within 1 % of) a bound of the search box
    (``on_bound``: {name: (side, bound)}), and how to widen it (``widen``: the way to say it,
    default the ``bounds=`` argument of :func:`tuning.design.tune.tune`); None when there is
    none."""
    if not on_bound:
        return None
    parts = [
        f"{n} = {getattr(gains, n):.4g} on its {side} bound {b:g}"
        for n, (side, b) in on_bound.items()
    ]
    if widen is None:
        wider = ", ".join(
            f"{n!r}: ({bounds[n][0]:g}, {bounds[n][1] * 4:g})"
            if side == "upper"
            else f"{n!r}: ({bounds[n][0] / 4:g}, {bounds[n][1]:g})"
            for n, (side, _) in on_bound.items()
        )
        widen = f"bounds={{{wider}}}"
    return (
        "on a bound: " + "; ".join(parts) + f" (the search box limits this result: widen "
        f"it with {widen} to see whether it improves)"
    )


def progress_printer(progress):
    """report(entry) for :func:`tuning.design.iteration.descend`: ``progress`` a callable
    (given each history dict), True (a status line on stderr: rewritten in place on a
    terminal, every 2 s otherwise) or False (silent); report(None) ends the line."""
    if callable(progress):
        return lambda entry: entry is not None and progress(entry)
    if not progress:
        return lambda entry: None
    stream = sys.stderr
    tty = stream.isatty()
    state = {"last": -1.0}

    def report(entry):
        if entry is None:
            if tty:
                print(file=stream, flush=True)
            return
        now = entry["seconds"]
        if tty and now - state["last"] < 0.1:
            return
        if not tty and now - state["last"] < 2.0:
            return
        state["last"] = now
        best = entry["best_settling_time"]
        best_text = f"{best:.3f} s" if math.isfinite(best) else "none yet"
        text = (
            f"tune: it {entry['iteration']:4d}  width x{entry['scale']:.3f}  "
            f"loss {entry['loss']:.4f}  smooth settling {entry['settling_time']:.3f} s  "
            f"overshoot {entry['overshoot']:.2f} %  best meeting spec {best_text}  "
            f"{now:.1f} s"
        )
        print(("\r" if tty else "") + text, end="" if tty else "\n", file=stream, flush=True)

    return report
