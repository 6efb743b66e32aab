"""Pytree registrations of types defined in hw/ (numpy only, so it cannot register them).

Imported by every module that traces a controller (:mod:`jaxcart.smooth_sim` and through it
everything that simulates), so the registration happens before any JAX transformation sees a PID.
A module runs once per process, so the registration does too.
"""

import jax

from hw.control_law import PID, PID_DATA_FIELDS, PID_META_FIELDS

jax.tree_util.register_dataclass(
    PID, data_fields=list(PID_DATA_FIELDS), meta_fields=list(PID_META_FIELDS)
)
