"""The PID tuned for the cart as measured: robust over the fitted cart's uncertainty, inside
limits derived from the cart, then predicted with its band and its margins.

    CartUncertainty --draw--> the fitted cart + N_TRAIN drawn carts (the sensor left out: the
        |                     tuner's loop reads the position itself)
        |                          |
        |        tune(robust=those carts; its box's kp and kd from the cart): the soft worst case
        |                          |
        '--> predict (N_CARTS other carts, exact simulator) + margins + the limit that binds

One tuner (:func:`tuning.design.tune.tune`, its settings :data:`tuning.design.settings.DEFAULT`):
the loss is its soft maximum over the drawn carts, so the design meets the spec on the worst of
them, with the settling time as short as that worst case allows. The carts it is judged on
afterwards (:func:`tuning.design.prediction.predict`) are others, drawn with another seed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from hw.control_law import PID
from tuning.design.losses import Spec
from tuning.design.margins import Margins, margins
from tuning.design.prediction import N_CARTS, Prediction, predict
from tuning.design.tune import tune
from tuning.design.uncertainty import CartUncertainty

#: Carts drawn for the robust loss, besides the fitted one.
N_TRAIN = 11
#: The training carts are drawn this much wider than the fit says: 1, as it says (the worst of
#: 12 such carts is about the 92nd percentile of the fit's carts; wider draws make the design
#: more cautious, and with a drive that varies much from run to run, some of them carts no
#: design moves 0.5 m in a second). Their drive values are normal of the scale the prediction's
#: t has (:meth:`~tuning.design.uncertainty.CartUncertainty.draw`): from two runs the t has one
#: degree of freedom, and the worst of a dozen such draws (the real cart's amplifier limit,
#: 5.09 and 5.90 V in two runs: below 1.5 V one time in twenty) would set the design alone.
TRAIN_WIDTH = 1.0
#: The design keeps its overshoot under this fraction of the settling band. The settling time
#: jumps where the overshoot crosses the band: a design tuned to settle fastest overshoots just
#: inside it (1.8-2.0 % of a 2 % band), and a true cart that overshoots a little more than
#: predicted leaves the band and settles one oscillation later (the independent generator's
#: carts: 64-225 ms late, outside their bands). Under half the band, a true overshoot up to
#: twice the predicted one still settles where it first enters the band.
EDGE = 0.5


@dataclass(frozen=True, eq=False)
class CartDesign:
    """A design for the cart as measured: tuned (the :class:`tuning.design.result.TuneResult`),
    limits ({gain: :class:`tuning.design.limits.Limit`}), binding (which limit sets it, a
    sentence), prediction (:class:`tuning.design.prediction.Prediction` on other drawn carts)
    and margins (on the fitted cart)."""

    tuned: object
    limits: dict
    binding: str
    prediction: Prediction
    margins: Margins

    @property
    def gains(self) -> PID:
        return self.tuned.gains


def design_plant(plant):
    """The cart as the tuner's design model: its mechanics and drive without the sensor."""
    return dataclasses.replace(
        plant, effects=tuple(e for e in plant.effects if e.stage != "sensor")
    )


def training_carts(uncertainty: CartUncertainty, n: int = N_TRAIN, *, seed: int = 0) -> list:
    """The fitted cart (its drive at the runs' mean) and ``n`` carts drawn :data:`TRAIN_WIDTH`
    times as wide as the fit says, as design models (:func:`design_plant`)."""
    wide = uncertainty.scaled(TRAIN_WIDTH)
    drawn = [wide.cart(v) for v in wide.draw(n, seed=seed, tails=False)]
    return [design_plant(p) for p in [uncertainty.nominal_cart(), *drawn]]


def clear_of_the_edge(spec: Spec) -> Spec:
    """``spec`` with its overshoot bound at most :data:`EDGE` times the settling band [%]: the
    design is tuned to it and judged (predicted, checked) against ``spec`` itself."""
    return dataclasses.replace(spec, overshoot=min(spec.overshoot, 100.0 * EDGE * spec.band))


def design_for_cart(
    uncertainty: CartUncertainty,
    *,
    spec: Spec | None = None,
    controller: PID | None = None,
    start=None,
    free=("kp", "kd", "ki"),
    n_train: int = N_TRAIN,
    n_predict: int = N_CARTS,
    seed: int = 0,
    executor=None,
    progress=False,
    **search,
) -> CartDesign:
    """Tune the PID for the cart of ``uncertainty``: robust over ``n_train`` drawn carts and
    the fitted one (seed ``seed``), inside the limits :func:`tuning.design.limits.gain_limits`
    derives from the fitted cart (the tuner's box), then
    predicted on ``n_predict`` others (seed ``seed + 1``) with its margins. ``spec``,
    ``controller`` (the settings that are not tuned; default the lab's: tau 0.01 s, 6 V),
    ``start``, ``free`` and ``search`` (n_starts, max_iterations, ...) as
    :func:`tuning.design.tune.tune` takes them; ``executor``: what makes the prediction's
    exact runs (the caller's :class:`jaxcart.workers.Helpers`)."""
    spec = spec or Spec()
    controller = controller or PID(tau=0.01, v_limit=6.0)
    carts = training_carts(uncertainty, n_train, seed=seed)
    tuned = tune(
        carts[0],
        spec=clear_of_the_edge(spec),
        start=start,
        free=free,
        controller=controller,
        robust=carts,
        seed=seed,
        progress=progress,
        **search,
    )
    prediction = predict(
        uncertainty, tuned.gains, spec, n=n_predict, seed=seed + 1, executor=executor
    )
    return CartDesign(
        tuned,
        tuned.limits,
        tuned.binding,
        prediction,
        margins(uncertainty.nominal_cart(), tuned.gains),
    )
