"""What the recordings cover: the data conditions under which an effect can be told apart.

An effect is worth a candidate's fit only where the recordings can show it: a map of the
friction along the track needs the track covered (``Effect.covers`` [m]); a difference between
the two directions needs motion both ways (``Effect.needs``: "both_ways"), or the drive pushing
both ways ("drive_both_ways"); a tilted track is a drive offset in every driven run and shows
itself only where a tap (motor unplugged) is among the recordings ("tap"). The
conditions are measured once per diagnosis (:meth:`Coverage.of`) and each effect's are checked
by :func:`tuning.estimation.diagnose.structures.candidate_list`; an effect left out is one fewer
structure in every batch (the search's rounds are padded to round 1's size).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The cart counts as sliding one way where it moves faster than this, over STEP [m/s].
SLIDING = 0.005
#: Positions are differenced over this span [s] (encoder counts of 23 um at 1 kHz).
STEP = 0.01
#: The cart moves both ways where it travels at least this far sliding in each direction [m]
#: ...
BOTH_WAYS = 0.005
#: ... and the lesser direction at least this share of the greater: a step's overshoot (a
#: clean PID step of the independent generator slides back a few mm of its 0.4 m) determines
#: no difference between the directions, and an asymmetry fitted to it absorbs what the cart
#: does not repeat (named there at 0.034 mm against 0.038 mm for the baseline: a false alarm).
BOTH_WAYS_SHARE = 0.2
#: The drive pushes both ways where its command reaches this much of each sign [V] (a dead band
#: of the motor's brushes is a few tenths of a volt).
PUSH = 0.5

#: The data conditions an effect may declare (``Effect.needs``), in words.
NEEDS = {
    "both_ways": (
        f"the cart slides both ways (at least {BOTH_WAYS * 1e3:g} mm each way, the lesser "
        f"{BOTH_WAYS_SHARE:.0%} of the greater)"
    ),
    "drive_both_ways": f"the drive pushes both ways (commands beyond +-{PUSH:g} V)",
    "tap": "a recording with the motor unplugged (a tap)",
}


@dataclass(frozen=True)
class Coverage:
    """What a set of recordings covers.

    span: the range of their positions together [m]; right, left: the distance the cart slides
    towards +y and -y, over every recording [m]; push_right, push_left: the largest command
    towards +y and -y of the driven runs' recorded commands [V] (a run without one adds
    nothing); motorless, driven: a recording with the motor unplugged, one with it
    connected."""

    span: float = 0.0
    right: float = 0.0
    left: float = 0.0
    push_right: float = 0.0
    push_left: float = 0.0
    motorless: bool = False
    driven: bool = False

    @classmethod
    def of(cls, segments, commands) -> Coverage:
        """The coverage of prepared ``segments`` (:class:`~.segments.Segment`); ``commands``: each
        segment's command [V] or None (a tap, or a command neither recorded nor replayable)."""
        ys = [np.asarray(s.target, dtype=float) for s in segments]
        right = left = 0.0
        for seg, y in zip(segments, ys, strict=True):
            k = max(int(round(STEP / float(seg.experiment.sample_time))), 1)
            d = np.diff(y[::k])
            moving = np.abs(d) > SLIDING * STEP
            right += float(np.sum(d[moving & (d > 0)]))
            left -= float(np.sum(d[moving & (d < 0)]))
        pushes = [np.asarray(u, dtype=float) for u in commands if u is not None]
        pushes = [u[np.isfinite(u)] for u in pushes if u.size]
        return cls(
            span=float(np.ptp(np.concatenate(ys))) if ys else 0.0,
            right=right,
            left=left,
            push_right=max((float(u.max()) for u in pushes if u.size), default=0.0),
            push_left=max((float(-u.min()) for u in pushes if u.size), default=0.0),
            motorless=any(not s.motor for s in segments),
            driven=any(s.motor for s in segments),
        )

    def shows(self, need: str) -> bool:
        """Whether the recordings meet the data condition ``need`` (:data:`NEEDS`)."""
        if need == "both_ways":
            less, more = sorted((self.right, self.left))
            return less >= BOTH_WAYS and less >= BOTH_WAYS_SHARE * more
        if need == "drive_both_ways":
            return min(self.push_right, self.push_left) >= PUSH
        if need == "tap":
            return self.motorless
        raise ValueError(f"unknown data condition {need!r}: one of {', '.join(NEEDS)}")

    def lacks(self, cls) -> str:
        """Why the effect class ``cls`` cannot be told apart in these recordings ("" when it
        can): the stretch of track it ``covers``, or a condition it ``needs``."""
        if cls.covers and self.span < cls.covers:
            return (
                f"the recordings cover {self.span:.3g} m of the track, under the {cls.covers:g} m "
                "a map along it needs"
            )
        missing = [NEEDS[n] for n in cls.needs if not self.shows(n)]
        return f"it needs {' and '.join(missing)}" if missing else ""
