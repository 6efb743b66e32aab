"""Recordings prepared for fitting: the one :class:`Segment` and :func:`prepare` of every fit
of the engine (``jaxcart fit`` and ``jaxcart diagnose``): a tap's coasting part and its start
state, a driven run whole, every position the middle of its encoder count."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from hw.control_law import PID
from jaxcart.errors import UserError
from jaxcart.files import signal64
from jaxcart.parallel import put
from jaxcart.params import ENCODER_RESOLUTION
from jaxcart.plantspec import build_plant
from tuning.estimation.engine import parameters
from tuning.estimation.engine.noise import encoder_count


@dataclass(eq=False)
class Segment:
    """One recording prepared for fitting: the samples ``start:stop`` of it.

    name: the recording's file name; kind: "tap", "closed_loop" or "open_loop"; experiment:
    the part fitted as an :class:`~jaxcart.experiments.Experiment` (y0, yd0 the start guesses);
    controller: the PID that ran (a placeholder for taps and open loop); target: measured
    positions, the middle of each count [m]; time: recording time of each sample [s];
    quantization: the encoder count found in the data [m] (0: not quantized); motor: the
    motor drives the cart (not a tap); counts_in_loop: the controller reads the recorded
    counts, so the plant's quantization sensor is in the loop and the simulated position is
    compared, not the reading (:func:`counts_in_loop`).

    A fit of fixed structure (:func:`tuning.estimation.fit.fit`) adds its own: ``plant``, the
    plant the recording ran on with the start values; ``nuisance``, the per-recording values
    fitted beside the plant (:class:`tuning.estimation.fitting.model.Nuisance`); ``params``,
    the fitted parameters that act on this plant.
    """

    name: str
    kind: str
    experiment: object
    controller: object
    target: np.ndarray
    time: np.ndarray
    start: int
    stop: int
    quantization: float
    counts_in_loop: bool = False
    plant: object = None
    nuisance: tuple = ()
    params: tuple = ()

    @property
    def motor(self) -> bool:
        return self.kind != "tap"


def recording_name(recording) -> str:
    """The recording's file name ("recording" where it has none)."""
    path = getattr(recording, "path", None)
    return str(getattr(path, "name", path) or "recording")


def prepare(
    recording, controller=None, *, quantization=None, margin: float = 0.02, min_coasting: int = 20
) -> Segment:
    """``recording`` as a :class:`Segment`: a tap's coasting part (:func:`coasting_segment`,
    ``margin`` [s] after the push; at least ``min_coasting`` samples) with its start state
    (:func:`initial_state`), or a closed or open loop's whole run (y0: the first position).
    controller: the PID that ran (default the recording's); quantization: the encoder count
    [m] (None: found in the data, :func:`~.noise.encoder_count`)."""
    name = recording_name(recording)
    raw = np.asarray(recording.position, dtype=float)
    n = raw.size
    if n < 10:
        raise UserError(f"{name}: only {n} samples; a fit needs a recording of at least 10")
    if not np.all(np.isfinite(raw)):
        raise UserError(f"{name}: column y has non-finite values; remove those rows")
    q = encoder_count(raw) if quantization is None else float(quantization)
    y = raw + q / 2  # a count says the cart is somewhere in [y, y + q): the middle
    ts = float(recording.sample_time)
    time = np.asarray(recording.time, dtype=float)
    exp = recording.experiment
    if recording.kind == "tap":
        start, stop = _coasting(name, raw, ts, time, margin, q, min_coasting)
        y0, yd0 = initial_state(time, y, start)
    else:
        start, stop = 0, n
        y0, yd0 = float(y[0]), float(exp.yd0)
    signal = put(signal64(recording)[start:stop], float)
    experiment = dataclasses.replace(exp, signal=signal, y0=y0, yd0=yd0)
    if controller is None:
        controller = recording.controller
    if controller is None:
        controller = PID(sample_time=ts)
    return Segment(
        name, recording.kind, experiment, controller, y[start:stop], time[start:stop],
        start, stop, q,
    )  # fmt: skip


def _coasting(name, raw, ts, time, margin, q, least) -> tuple[int, int]:
    """(start, stop) of a tap's coasting part, or a UserError saying why there is none."""
    try:
        start, stop = coasting_segment(raw, ts, margin=margin, quantization=q or ENCODER_RESOLUTION)
    except ValueError as exc:
        raise UserError(f"{name}: {exc}; check that column y is the cart position") from None
    if stop - start < least:
        raise UserError(
            f"{name}: the coasting part found ({time[start]:.3f} s to {time[stop - 1]:.3f} s) "
            f"is shorter than {least} samples; record a longer tap"
        )
    return start, stop


def coasting_segment(
    position, sample_time: float, *, margin: float = 0.02, quantization: float = ENCODER_RESOLUTION
) -> tuple[int, int]:
    """The coasting part of a tap recording as sample indices (start, stop).

    start: ``margin`` [s] after the peak speed (the end of the push: the hand's force is gone
    once the cart outruns it); stop: the first sample from which the cart makes no further
    progress in its direction for 50 ms (rest), plus the samples it then stays within one count
    of rest (at most 50 ms; a real cart may then drift back). Raises UserError without motion.
    """
    y = np.asarray(position, dtype=float)
    n = y.size
    w = max(3, int(round(0.01 / sample_time)))  # 10 ms moving average of the velocity
    v = np.gradient(y, sample_time)
    kernel = np.ones(w) / w
    padded = np.concatenate([np.full(w, v[0]), v, np.full(w, v[-1])])
    v_smooth = np.convolve(padded, kernel, mode="same")[w:-w]
    peak = int(np.argmax(np.abs(v_smooth)))
    count = quantization if quantization > 0 else 1e-6
    if abs(v_smooth[peak]) * 0.05 < 3 * count:  # under 3 counts in 50 ms: no tap
        if np.ptp(y) > 100 * count:  # it moves, but slower than any push: the time's unit
            raise ValueError(
                f"no tap found: the cart moves {np.ptp(y):.3g} m but never faster than "
                f"{abs(v_smooth[peak]):.3g} m/s (the sample time is {sample_time:g} s: time "
                "recorded in ms? give t in s)"
            )
        raise ValueError("no tap found: the cart never moves more than a few encoder counts")
    direction = np.sign(v_smooth[peak])
    start = min(peak + int(round(margin / sample_time)), n - 2)
    z = direction * y
    window = max(2, int(round(0.05 / sample_time)))
    # Running maximum of what is still to come: rest where nothing ahead exceeds the present.
    ahead = np.maximum.accumulate(z[::-1])[::-1]
    stop = n - 1
    for k in range(start, n - 1):
        if ahead[min(k + 1, n - 1)] <= z[k] and np.all(z[k : k + window] <= z[k]):
            stop = k
            break
    end = stop
    while end + 1 < n and end - stop < window and abs(y[end + 1] - y[stop]) <= 1.01 * count:
        end += 1
    return start, end + 1


def initial_state(time, y, start):
    """(y0, yd0) at sample ``start`` from a quadratic over the next 20 ms [m, m/s]."""
    k = min(y.size - start, max(5, int(round(0.02 / (time[1] - time[0]))) + 1))
    t = time[start : start + k] - time[start]
    coef = np.polyfit(t, y[start : start + k], 2 if k > 5 else 1)
    return float(np.polyval(coef, 0.0)), float(np.polyval(np.polyder(coef), 0.0))


def counts_in_loop(base_plants, segments, read_counts) -> tuple[list, list]:
    """(base plants, segments), with the encoder's quantization in the loop where the recorded
    command shows that the controller read the recorded counts (``read_counts``, one per
    recording: controller.reads_counts), unless the plant models its sensor already.

    Feeding the controller the exact position instead biases its input by half a count (the
    mean of the floor) and loses the hunting between counts that integral action and friction
    make, which the search otherwise explains with effects that are not there. Such a
    simulation records what its controller read, whole counts; the diagnosis compares the
    cart's position instead (:func:`exact_residuals`), whose forward differences the exact
    polish needs (docs/diagnose.md, "The encoder in the loop")."""

    plants, segs = [], []
    for plant, seg, counts in zip(base_plants, segments, read_counts, strict=True):
        q = seg.quantization
        sensor, count = parameters.encoder()
        modelled = sensor in plant.structure  # a plant file's own sensor
        if counts and q > 0 and not modelled:
            plant = build_plant({count: q}, base=plant, check=False)
        if q > 0 and (modelled or counts):
            seg = dataclasses.replace(seg, counts_in_loop=True)
        plants.append(plant)
        segs.append(seg)
    return plants, segs
