"""Synthetic recordings: the exact simulator seen through the cart's encoder (and optional noise).

A synthetic recording is what the lab's data logger would have written had the cart been the
model: the exact (event-exact stick-slip, hard clip) run of :func:`jaxcart.exact.simulate_exact`,
its position read by an incremental encoder of resolution q [m/count] that reads 0 at the start,

    y(0) = y0 + phase,  y_measured = q floor(y / q) + noise,  phase ~ U[0, q),  noise ~ N(0, s^2)

where ``phase`` (where the cart starts within its count) and the noise are drawn from ``seed``;
with ``noise = 0`` the samples are whole counts, like the real recordings. Positions are in the
encoder's frame, the one the reference is given in. The controller of a closed-loop run acts on
the exact position y (the real one saw whole counts: a difference of less than kp * q in the
command, 1.1 mV at kp = 50 V/m, a force of 2 mN against friction of tenths of a newton).
Because the reference is in the encoder's frame, a closed-loop cart comes to rest at the same
place among the counts whatever the seed: for independent repetitions (checking standard
errors over many seeds) draw the plant or the experiment from the seed too.

The result is a :class:`jaxcart.files.Recording` (what :func:`jaxcart.files.read_experiment`
returns) plus the truth, so fitting and analysis code treat both alike; :func:`write_recording`
stores it as an experiment file (TOML + CSV).

>>> import jaxcart as jc
>>> rec = make_recording(jc.tap_plant(B_eq=3.0), None, jc.tap(1.0, horizon=0.5), seed=1)
>>> rec.kind, rec.position.shape
('tap', (501,))
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from hw.control_law import PID
from jaxcart.exact import simulate_exact
from jaxcart.experiments import Experiment
from jaxcart.files import Recording, write_experiment
from jaxcart.params import ENCODER_RESOLUTION, Plant
from jaxcart.smooth_sim import Response


@dataclass(frozen=True, eq=False, kw_only=True)  # kw_only: Recording's last fields have defaults
class SyntheticRecording(Recording):
    """A :class:`jaxcart.files.Recording` made by simulation, with its truth.

    truth: the plant that was simulated; true_position: y before the encoder [m] (in its frame,
    the cart started at the experiment's y0 plus ``phase``);
    quantization: encoder resolution q [m/count] (0: none); noise: standard deviation of the
    added white noise [m]; seed: the random seed of phase and noise.
    """

    truth: Plant
    true_position: np.ndarray
    quantization: float
    noise: float
    seed: int | None

    def response(self) -> Response:
        """The recording as a :class:`jaxcart.Response` (measured position; for
        :func:`jaxcart.files.write_experiment` and the plot helpers)."""
        n = self.n_samples
        zeros = np.zeros(n)
        command = zeros if self.command is None else self.command
        reference = np.full(n, self.position[0]) if self.reference is None else self.reference
        velocity = zeros.copy()
        velocity[0] = float(self.experiment.yd0)
        return Response(
            time=self.time,
            position=self.position,
            velocity=velocity,
            reference=reference,
            error=reference - self.position,
            command=command,
            voltage=command,
            diverged=False,
            kind=self.kind,
        )


class Encoder:
    """The cart's incremental encoder as the generator draws it from a seed.

    quantization: count size q [m] (0: none); noise: white-noise standard deviation [m];
    seed: draws ``phase`` (where the cart starts within its count, U[0, q)) and the noise.
    """

    def __init__(self, quantization: float = ENCODER_RESOLUTION, noise: float = 0.0, seed=0):
        if not (math.isfinite(quantization) and quantization >= 0):
            raise ValueError(f"quantization = {quantization!r} m: give a count size >= 0")
        if not (math.isfinite(noise) and noise >= 0):
            raise ValueError(f"noise = {noise!r} m: give a standard deviation >= 0")
        self.quantization, self.noise, self.seed = float(quantization), float(noise), seed
        self._rng = np.random.default_rng(seed)
        self.phase = float(self._rng.uniform(0.0, quantization)) if quantization > 0 else 0.0

    def read(self, position) -> np.ndarray:
        """What it reports for positions y [m] in its own frame: q floor(y / q) + noise."""
        y = np.asarray(position, dtype=np.float64)
        q = self.quantization
        if q > 0:
            # A position that is already a whole count (a truth whose controller reads this
            # encoder records what it read) stays that count: y / q may round to just below it.
            counts = y / q
            nearest = np.round(counts)
            y = q * np.where(np.abs(counts - nearest) < 1e-9, nearest, np.floor(counts))
        if self.noise > 0:
            y = y + self._rng.normal(0.0, self.noise, size=y.shape)
        return y


def make_recording(
    plant: Plant,
    controller: PID | None,
    experiment: Experiment,
    *,
    quantization: float = ENCODER_RESOLUTION,
    noise: float = 0.0,
    seed: int | None = 0,
    description: str | None = None,
) -> SyntheticRecording:
    """Run ``experiment`` on ``plant`` with the exact simulator and record it through an encoder.

    plant: the truth (:class:`jaxcart.Plant`); controller: the :class:`jaxcart.PID` of a closed
    loop (None otherwise); experiment: any :class:`jaxcart.Experiment` (the cart starts at its
    y0 plus the encoder's random phase); quantization: encoder count [m] (0 for none); noise:
    white noise standard deviation [m]; seed: random phase of the encoder and noise. The
    recording's ``command`` is the voltage the software sent [V] (closed and open loop), its
    ``reference`` the reference [m] (closed loop).
    """
    enc = Encoder(quantization, noise, seed)
    start = dataclasses.replace(experiment, y0=float(experiment.y0) + enc.phase)
    response = simulate_exact(plant, controller, start)
    if response.diverged:
        raise ValueError("the simulated run diverged; choose a stable controller")
    command = None if experiment.kind == "tap" else np.asarray(response.command)
    return _recording(plant, controller, experiment, response.position, command, enc, description)


def make_tap_recording(
    plant: Plant,
    *,
    speed: float = 1.0,
    rest: float = 0.5,
    push_time: float = 0.1,
    horizon: float = 2.0,
    sample_time: float = 0.001,
    quantization: float = ENCODER_RESOLUTION,
    noise: float = 0.0,
    seed: int | None = 0,
    description: str | None = None,
) -> SyntheticRecording:
    """A tap test as the lab records it (Part (i)): the cart rests for ``rest`` [s], a hand
    pushes it with a constant force for ``push_time`` [s] to ``speed`` [m/s], then it coasts
    (motor unplugged) until ``horizon`` [s] has been recorded.

    plant: the truth, normally :func:`jaxcart.tap_plant` with a :class:`jaxcart.Coulomb` effect.
    The push force is whatever reaches ``speed`` at the end of the push against the plant's
    viscous and Coulomb friction. The recording's experiment is the tap as a file describes it
    (cart at rest at t = 0, no drive): a simulator cannot reproduce the unknown push; fitting
    finds the coasting part itself.
    """
    if not (speed > 0 and rest >= 0 and push_time > 0 and horizon > rest + push_time):
        raise ValueError(
            "make_tap_recording: need speed > 0, rest >= 0, push_time > 0 and "
            "horizon > rest + push_time"
        )
    n = int(round(horizon / sample_time)) + 1
    k_push = int(round(rest / sample_time))
    k_coast = k_push + max(1, int(round(push_time / sample_time)))
    m, c = float(plant.m), float(plant.c)
    # Constant force F from rest: m y'' + c y' = F - f_c (moving forward throughout); only the
    # net force F - f_c matters, chosen to reach ``speed`` at the end of the push.
    tp = (k_coast - k_push) * sample_time
    a = c / m
    gain = tp / m if a == 0 else -math.expm1(-a * tp) / c  # velocity per newton at tp
    net = speed / gain  # F - f_c [N]

    def pushed(t):
        t = np.asarray(t, dtype=float)
        if a == 0:
            return net * t * t / (2 * m), net * t / m
        e = np.exp(-a * t)
        return net / c * (t - (1 - e) / a), net / c * (1 - e)

    y_push, _ = pushed(np.arange(k_coast - k_push + 1) * sample_time)
    y_end, v_end = (float(x) for x in pushed(tp))
    coast = Experiment(
        jnp.zeros(n - k_coast), y0=y_end, yd0=v_end, kind="tap", sample_time=sample_time
    )
    coast_y = np.asarray(simulate_exact(plant, None, coast).position)
    enc = Encoder(quantization, noise, seed)
    y = np.concatenate([np.zeros(k_push), y_push[:-1], coast_y]) + enc.phase
    experiment = Experiment(jnp.zeros(n), y0=0.0, yd0=0.0, kind="tap", sample_time=sample_time)
    if description is None:
        description = (
            f"synthetic tap: rest {rest} s, push {tp:.3f} s to {speed} m/s, coasting "
            f"(truth: {_truth_text(plant)})"
        )
    return _recording(plant, None, experiment, y, None, enc, description)


def write_recording(
    recording: SyntheticRecording,
    toml_path,
    *,
    force: bool = False,
    plant_overrides: dict | None = None,
) -> Path:
    """Write a synthetic recording as an experiment file (TOML + CSV beside it) with
    :func:`jaxcart.files.write_experiment`; refuses to overwrite unless ``force``.
    ``plant_overrides`` go to [plant] (the truth is named in the description, not in [plant],
    so that a fit of the file starts from the nominal plant)."""
    return write_experiment(
        toml_path,
        recording.response(),
        controller=recording.controller,
        plant_overrides=plant_overrides,
        description=recording.meta.get("description"),
        force=force,
    )


def _truth_text(plant: Plant) -> str:
    names = ("M", "B_eq", "gamma_scale", "f_c", "v_sat")
    present = [n for n in names if n in plant.param_names()]
    return ", ".join(f"{n} = {float(plant.get(n)):.6g}" for n in present)


def _recording(
    plant, controller, experiment, true_position, command, enc: Encoder, description
) -> SyntheticRecording:
    true_position = np.asarray(true_position, dtype=np.float64)
    measured = enc.read(true_position)
    n = measured.shape[0]
    ts = float(experiment.sample_time)
    kind = experiment.kind
    if description is None:
        description = f"synthetic {kind} (truth: {_truth_text(plant)})"
    meta = {"kind": kind, "sample_time": ts, "description": description}
    reference = None
    if kind == "closed_loop":
        reference = np.asarray(experiment.signal, dtype=np.float64)
    # The file's view: the experiment starts at the first measured position.
    exp = dataclasses.replace(experiment, y0=float(measured[0]))
    return SyntheticRecording(
        path=Path(f"<synthetic {kind}>"),
        kind=kind,
        sample_time=ts,
        time=np.arange(n) * ts,
        position=measured,
        command=command,
        reference=reference,
        controller=controller if kind == "closed_loop" else None,
        plant_overrides={},
        experiment=exp,
        meta=meta,
        truth=plant,
        true_position=true_position,
        quantization=enc.quantization,
        noise=enc.noise,
        seed=enc.seed,
    )
