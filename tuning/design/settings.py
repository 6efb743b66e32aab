"""How the tuner searches, in one place: the defaults of :func:`tuning.design.tune.tune`, which
``jaxcart tune``, the lab's pre-lab and its re-tune on the fitted cart all use, so that the same
problem gets the same gains from each (one tuner, one answer).

Imports nothing but the standard library: the command line's parser reads its defaults here
without starting jax.
"""

from __future__ import annotations

from typing import NamedTuple


class TuneSettings(NamedTuple):
    """n_starts: starts in the batch (the given one, a pole-placement design for the plant
    (:func:`tuning.design.problem.model_start`) and log-normal perturbations of the given one's
    free parameters; ``spread``: the standard deviation of their logs); max_iterations: the most
    iterations; learning_rate: adam's step in log parameter (0.25 is a 25 % step), decayed
    along a cosine to a tenth of it over ``max_iterations``; stage_iterations: the most
    iterations at one smoothing width (fewer once the parameters stop moving); patience:
    iterations at the finest width without a better point before stopping; check_every:
    iterations between looks at the exact-threshold metrics that pick the candidates; seed:
    of the starts (and of the random plants a robust result is checked on)."""

    n_starts: int = 8
    spread: float = 0.5
    max_iterations: int = 400
    learning_rate: float = 0.25
    patience: int = 8
    stage_iterations: int = 10
    check_every: int = 1
    seed: int = 0


#: The tuner's settings wherever nothing else is asked for.
DEFAULT = TuneSettings()
