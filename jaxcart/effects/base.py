"""What an effect is: a small piece of physics with an exact and a smoothed form.

Each effect is a frozen dataclass registered as a pytree (its parameters are array leaves, so
they can be fitted, vmapped and differentiated) and acts at one place of the loop:

    controller --u--> [voltage effects] --v_applied--> gamma * v_applied + [force effects] --> cart
        ^                                                                                    |
        '------------------------------ [sensor effects] <---------------- y ---------------'

- ``stage = "voltage"``: ``smooth(v, smoothing)`` (JAX) and ``exact(v)`` (numpy) map the commanded
  voltage to the voltage the motor sees.
- ``stage = "force"``: ``smooth_force(y, ydot, smoothing)`` (JAX) is the force on the cart [N];
  the exact simulator reads ``friction_levels()`` -> (kinetic, static) [N] for stick-slip.

Adding an effect is one module: the dataclass, its two forms, and its entry in ``__init__``.
"""

from __future__ import annotations

from typing import ClassVar


class Effect:
    """Base class of effects (documentation and shared helpers)."""

    stage: ClassVar[str] = ""
    #: names of the fields that are physical parameters (fittable; unique across effects)
    param_names: ClassVar[tuple[str, ...]] = ()
