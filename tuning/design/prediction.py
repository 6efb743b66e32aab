"""The step of a design on the cart as measured, with its band: what a student may expect when
the design runs on the cart.

    CartUncertainty --draw n carts--> [the fitted cart, cart 1 ... cart n]
                                          | each: the exact simulator, the design's step
                                          v
        the fitted cart's step (nominal) + the band of the n steps (position over time, each
        metric) + the chance of meeting the spec + each value's sensitivity

The band is a prediction interval: of ``n`` drawn carts' results, the k-th smallest and k-th
largest with k = floor((n + 1)(1 - level)/2), so that a new cart drawn like them (the true one,
when the fit's errors are what its covariance says) lies inside with probability at least
``level`` (order statistics: (n + 1 - 2k)/(n + 1); n = 19 at 90 %: the least and the most).
The spec (:class:`tuning.design.losses.Spec`) is the lab's: settling under 1 s in the 2 % band,
overshoot under 5 %, the command within the drive's 6 V and the cart within the track's 0.814 m
travel. Every run is :func:`jaxcart.exact.simulate_exact`'s; they are independent, and made
through the caller's ``executor`` (:class:`jaxcart.workers.Helpers`) when given one.

:func:`predict` computes; :func:`tuning.design.prediction_plot.plot_prediction` draws.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import numpy as np
from scipy.stats import t as student_t

from hw.control_law import float_pid
from jaxcart.exact import simulate_exact
from jaxcart.experiments import step
from jaxcart.metrics import step_info
from jaxcart.params import TRAVEL
from jaxcart.plantspec import unit
from jaxcart.workers import SERIAL
from tuning.design.losses import Spec
from tuning.design.uncertainty import CartUncertainty

#: Carts drawn for a band: 63 gives the 90 % band as the 3rd least and 3rd most (a new cart
#: inside with probability 60/64 = 0.94 >= 0.9).
N_CARTS = 63
#: The band's level: the probability that a new cart drawn like these lies inside.
LEVEL = 0.9
#: The metrics a band is given for: settling time [s], overshoot [%], peak command [V],
#: excursion (how far the cart moves from its start at most) [m].
METRICS = ("settling_time", "overshoot", "peak_voltage", "excursion")
#: The drive's voltage range [V] (a command beyond it is not met by the drive).
V_RANGE = 6.0


@dataclass(frozen=True, eq=False)
class Prediction:
    """One design's step on the cart as measured.

    controller: the design (a PID); spec; level; time [s]; reference [m]; nominal: the fitted
    cart's position [m] and command [V] (``nominal_position``, ``nominal_command``) and its
    metrics ({name: value}); band: (low, high) of the position [m] at each time; metrics:
    {name: array over the drawn carts} of :data:`METRICS`; meets: whether each drawn cart meets
    the spec; values: each drawn cart's varied values; sensitivity: {name: {"stderr" [SI],
    metric: change per standard error}} at the fitted cart (central differences, one standard
    error each way); experiment: what was simulated; model_error: {metric: how far the model
    misses the cart's own recorded steps} (:mod:`tuning.design.calibration`; {} without
    recordings), by which :meth:`interval` and :meth:`position_band` widen the fit's band."""

    controller: object
    spec: Spec
    level: float
    time: np.ndarray
    reference: np.ndarray
    nominal_position: np.ndarray
    nominal_command: np.ndarray
    nominal: dict
    band: tuple
    metrics: dict
    meets: np.ndarray
    values: list = field(default_factory=list)
    sensitivity: dict = field(default_factory=dict)
    experiment: object = None
    model_error: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Carts drawn."""
        return int(self.meets.size)

    @property
    def p_meet(self) -> float:
        """The chance that a run of the design meets the spec: the mean over the drawn carts
        of each one's chance with its settling time and overshoot shifted by a new run's miss
        of the model (:attr:`model_error`: the recorded steps' RMS miss times Student's t with
        as many degrees of freedom as steps, the bound's own assumption); without a model
        error (or a model error without its "steps", :func:`~tuning.design.calibration.
        model_error`'s degrees of freedom), the share of the drawn carts that meet it; the
        bound is taken at this prediction's level. On the real PD run alone (one step
        missed by 216 ms) the pre-lab's design, predicted at 0.88 s, meets a 1 s spec with a
        chance of 66 %, where 98 % of the drawn carts meet it."""
        if not self.meets.size:
            return math.nan
        steps = self.model_error.get("steps", {})
        if not any(self.model_error.get(m, 0.0) > 0 and steps.get(m, 0) for m in steps):
            return float(np.mean(self.meets))
        chance = np.asarray(within_reach(self.metrics), dtype=float)
        for metric, bound in (("settling_time", self.spec.settling_time),
                              ("overshoot", self.spec.overshoot)):  # fmt: skip
            value = np.asarray(self.metrics[metric], dtype=float)
            miss, n = float(self.model_error.get(metric, 0.0)), int(steps.get(metric, 0))
            if miss > 0 and n > 0:
                scale = miss / t_factor(n, self.level)
                # A run that never settles (inf) or has no overshoot to speak of (nan) fails.
                z = np.where(np.isfinite(value), (bound - value) / scale, -np.inf)
                chance = chance * student_t.cdf(z, n)
            else:
                chance = chance * (value < bound)
        return float(np.mean(chance))

    def fit_interval(self, metric: str) -> tuple[float, float]:
        """The band of ``metric`` over the drawn carts (:func:`band_of`): the fit's alone."""
        lo, hi = band_of(self.metrics[metric], self.level)
        return float(lo), float(hi)

    def interval(self, metric: str) -> tuple[float, float]:
        """The band of ``metric``: the fit's, widened on both sides by the model's error in it
        (:attr:`model_error`), no edge below 0: every metric of :data:`METRICS` is a time, a
        share or a magnitude (a PD run's one recorded step, missed by 216 ms, put a settling
        time's band at -0.56 to 2.31 s)."""
        lo, hi = self.fit_interval(metric)
        miss = float(self.model_error.get(metric, 0.0))
        return max(lo - miss, 0.0), hi + miss

    def position_band(self) -> tuple[np.ndarray, np.ndarray]:
        """The position's band [m] at each time: the fit's, widened in time by the model's
        error in the settling time (the least of the band's low edge and the most of its high
        edge within that many seconds either side)."""
        # lazy: scipy.ndimage costs 0.1-0.3 s at start-up (python -X importtime) in a helper
        # process, which imports this module alone for step_run; one path here needs it
        from scipy.ndimage import maximum_filter1d, minimum_filter1d

        lo, hi = (np.asarray(x, dtype=float) for x in self.band)
        dt = float(self.time[1] - self.time[0]) if self.time.size > 1 else 1.0
        k = int(round(float(self.model_error.get("settling_time", 0.0)) / dt))
        if k <= 0:
            return lo, hi
        size = 2 * k + 1
        return (
            minimum_filter1d(lo, size, mode="nearest"),
            maximum_filter1d(hi, size, mode="nearest"),
        )

    def to_json(self) -> dict:
        """The prediction as a gains file and ``jaxcart run`` read it (:mod:`hw.predicted`):
        for each metric its nominal value and band (the fit's and the model error's; the fit's
        alone as ``band_fit``), the chance of meeting the spec, each value's standard error and
        the metrics' change per standard error."""
        return {
            "level": self.level,
            "carts": self.n,
            "p_meet": self.p_meet,
            "spec": {"settling_time": self.spec.settling_time, "overshoot": self.spec.overshoot},
            "metrics": {m: self._metric_json(m) for m in METRICS},
            "step": float(self.reference[-1] - self.nominal_position[0]),
            "sensitivity": {
                n: {k: v if isinstance(v, str) else _plain(v) for k, v in s.items()}
                for n, s in self.sensitivity.items()
            },
        }

    def _metric_json(self, metric: str) -> dict:
        return {
            "nominal": _plain(self.nominal[metric]),
            "band": [_plain(x) for x in self.interval(metric)],
            "band_fit": [_plain(x) for x in self.fit_interval(metric)],
            "model_error": _plain(self.model_error.get(metric, 0.0)),
        }


def t_factor(n: int, level: float = LEVEL) -> float:
    """t_{(1+level)/2, n}: the bound on a new miss over the RMS of ``n`` misses at ``level``
    (6.31 for one at 90 %, 2.35 for three; :mod:`tuning.design.calibration`)."""
    return float(student_t.ppf((1.0 + level) / 2.0, n))


def _plain(x):
    x = float(x)
    return x if math.isfinite(x) else ("inf" if x > 0 else "-inf" if x < 0 else "nan")


def band_of(samples, level: float = LEVEL) -> tuple[float, float]:
    """(k-th least, k-th most) of ``samples`` with k = max(1, floor((n + 1)(1 - level) / 2)):
    a new draw of the same distribution falls inside with probability >= level (for
    n >= 2 / (1 - level) - 1)."""
    x = np.sort(np.asarray(samples, dtype=float), axis=0)
    n = x.shape[0]
    k = max(1, int(math.floor((n + 1) * (1.0 - level) / 2.0)))
    return x[k - 1], x[n - k]


def step_run(job) -> tuple:
    """One exact run of a design's step (a :meth:`jaxcart.workers.Helpers.map` job: ``(plant,
    controller, experiment)``): (position [m], command [V], {metric: value})."""
    plant, controller, experiment = job
    with jax.enable_x64(True):
        res = simulate_exact(plant, float_pid(controller), experiment)
    info = step_info(res, v_limit=float(controller.v_limit))
    y = np.asarray(res.position, dtype=float)
    u = np.asarray(res.command, dtype=float)
    metrics = {
        "settling_time": float(info.settling_time),
        "overshoot": float(info.overshoot),
        "peak_voltage": float(np.max(np.abs(u))) if not info.diverged else math.inf,
        "excursion": float(np.max(np.abs(y - y[0]))) if not info.diverged else math.inf,
        "diverged": bool(info.diverged),
    }
    return y, u, metrics


def meets_spec(metrics: dict, spec: Spec) -> bool:
    """The spec on one run's metrics: settling and overshoot under their bounds, the command
    within the drive's range, the cart within the track's travel."""
    return bool(
        not metrics["diverged"]
        and metrics["settling_time"] < spec.settling_time
        and metrics["overshoot"] < spec.overshoot
        and within_reach(metrics)
    )


def within_reach(metrics):
    """The spec's limits besides time and overshoot, on one run's metrics or arrays of them:
    the command within the drive's range and the cart within the track's travel (a diverged
    run's are inf: outside)."""
    return (metrics["peak_voltage"] <= V_RANGE * (1 + 1e-9)) & (metrics["excursion"] <= TRAVEL)


def predict(
    uncertainty: CartUncertainty,
    controller,
    spec: Spec | None = None,
    *,
    experiment=None,
    n: int = N_CARTS,
    level: float = LEVEL,
    seed: int = 0,
    sensitivity: bool = True,
    executor=None,
) -> Prediction:
    """The step of ``controller`` on the cart of ``uncertainty`` and on ``n`` carts drawn from
    it (:meth:`CartUncertainty.draw`, ``seed``), each on the exact simulator.

    spec: the design problem (default the lab's: 0.5 m, settling < 1 s, overshoot < 5 %);
    experiment: what to simulate (default the spec's step over its horizon; a recording's
    own experiment to predict that run); sensitivity: also each varied value's effect on the
    metrics (two runs per value); executor: what makes the runs (the caller's
    :class:`jaxcart.workers.Helpers`; default one after the other here)."""
    spec = spec or Spec()
    experiment = experiment or step(spec.step, horizon=spec.horizon)
    values = uncertainty.draw(n, seed=seed)
    plants = [uncertainty.nominal_cart()] + [uncertainty.cart(v) for v in values]
    names = list(uncertainty.varied) if sensitivity else []
    nominal = uncertainty.nominal()
    for name in names:
        se = uncertainty.stderr(name)
        for sign in (-1.0, 1.0):
            plants.append(uncertainty.cart({name: nominal[name] + sign * se}))
    jobs = [(_host(p), controller, experiment) for p in plants]
    runs = (executor or SERIAL).map(step_run, jobs)
    drawn = runs[1 : n + 1]
    positions = np.array([y for y, _, _ in drawn])
    y0, u0, m0 = runs[0]
    return Prediction(
        controller=controller,
        spec=spec,
        level=level,
        time=np.asarray(experiment.time, dtype=float),
        reference=np.asarray(experiment.signal, dtype=float),
        nominal_position=y0,
        nominal_command=u0,
        nominal=m0,
        band=band_of(positions, level),
        metrics={m: np.array([r[2][m] for r in drawn]) for m in METRICS},
        meets=np.array([meets_spec(r[2], spec) for r in drawn], dtype=bool),
        values=values,
        sensitivity=_sensitivities(uncertainty, names, runs[n + 1 :]),
        experiment=experiment,
    )


def _sensitivities(uncertainty, names, runs) -> dict:
    """{name: {"value" [SI], "unit", "stderr" [SI], metric: (metric at +1 se - metric at -1
    se) / 2}} (a metric that is inf either way: nan); a drive value drawn from Student's t
    also "dof", its degrees of freedom (``stderr`` is then the t's scale)."""
    out = {}
    nominal = uncertainty.nominal()
    for i, name in enumerate(names):
        low, high = runs[2 * i][2], runs[2 * i + 1][2]
        entry = {"value": nominal[name], "unit": unit(name), "stderr": uncertainty.stderr(name)}
        dof = uncertainty.drive_parts(name)[3] if name in uncertainty.drive else 0
        if dof:
            entry["dof"] = dof
        for m in METRICS:
            a, b = low[m], high[m]
            entry[m] = (b - a) / 2.0 if math.isfinite(a) and math.isfinite(b) else math.nan
        out[name] = entry
    return out


def _host(plant):
    """The plant with numpy leaves (a job pickles it for a helper process)."""
    return jax.tree.map(np.asarray, plant)
