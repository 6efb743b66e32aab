"""The one parameter layout of the estimation engine: which entry of a fitted vector is which
value, and which entries each recording reads.

Both ways of fitting use it: a fit of fixed structure (:mod:`tuning.estimation.fitting.model`,
its own parameters) and a diagnosis's batch of candidates (:mod:`tuning.estimation.engine.batch`,
the superset of every candidate's parameters). The vector holds, in order, the values shared by
every recording, each recording's own copies (``v_sat@2``: the drive's limit in recording 2
alone) and each recording's fitted start (``y0@0`` [m], ``yd0@0`` [m/s]); names as in
:mod:`tuning.estimation.engine.parameters`.
"""

from __future__ import annotations

from typing import NamedTuple

from tuning.estimation.engine import parameters

#: The batch's entry that unused slots of a candidate point at (never read by a recording).
DUMMY = "_dummy"


class Layout(NamedTuple):
    """names: every entry of the vector, in order; reads: per recording, (plant parameter,
    entry) of each parameter it reads, its own copy where it has one, else the shared value;
    starts: per recording, (start value, entry) of each fitted start ("y0", "yd0"), () where
    its start is given; per_recording: the parameters that get a copy per recording (a
    diagnosis's: its subsets are laid out alike). Hashable: a jit static."""

    names: tuple
    reads: tuple
    starts: tuple
    per_recording: tuple = ()

    @property
    def size(self) -> int:
        return len(self.names)

    @property
    def shared(self) -> tuple:
        """The entries shared by every recording, in order (in :func:`for_candidates`'s
        layout the first ones, so that a shared value's place here is its entry)."""
        return tuple(n for n in self.names if "@" not in n and n != DUMMY)

    @property
    def dummy(self) -> int:
        return self.names.index(DUMMY)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def own(self, i: int) -> tuple:
        """Recording ``i``'s own entries (its copies and its start values)."""
        return tuple(n for n in self.names if "@" in n and parameters.recording_of(n) == i)


def _reads(params, names, i) -> tuple:
    """(parameter, entry) of each of ``params`` in recording ``i``: its copy, else shared."""
    return tuple((p, names.index(f"{p}@{i}" if f"{p}@{i}" in names else p)) for p in params)


def for_fit(params, segments) -> Layout:
    """A fit's layout: its parameters ``params`` (canonical names, copies such as ``v_sat@1``
    among them, in the order given), then each segment's start values (``seg.nuisance``);
    each segment reads the parameters that act on its plant (``seg.params``)."""
    names = list(params)
    starts = []
    for k, seg in enumerate(segments):
        starts.append(tuple((v.name, len(names) + j) for j, v in enumerate(seg.nuisance)))
        names += [f"{v.name}@{k}" for v in seg.nuisance]
    reads = tuple(_reads(seg.params, names, k) for k, seg in enumerate(segments))
    return Layout(tuple(names), reads, tuple(starts))


def for_candidates(segments, per_recording=()) -> Layout:
    """A diagnosis's layout: the superset (:func:`~.parameters.superset`, from the registry
    as it is now: an effect registered later is in the next one's); then, for each name of
    ``per_recording``, a copy per recording it acts in (a drive parameter has none in a tap
    with the motor unplugged); then (y0, yd0) of each tap; then :data:`DUMMY`. Every
    recording reads every superset name."""
    shared = parameters.superset()
    names = list(shared)
    for i, seg in enumerate(segments):
        names += [f"{n}@{i}" for n in per_recording if seg.motor or not parameters.is_drive(n)]
    starts = []
    for i, seg in enumerate(segments):
        taps = seg.kind == "tap"
        starts.append((("y0", len(names)), ("yd0", len(names) + 1)) if taps else ())
        names += [f"y0@{i}", f"yd0@{i}"] if taps else []
    names.append(DUMMY)
    reads = tuple(_reads(shared, names, i) for i in range(len(segments)))
    return Layout(tuple(names), reads, tuple(starts), tuple(per_recording))
