"""Hardware side of jaxcart: numpy and the standard library only (never jax)."""

from hw.control_law import PID, PIDState, pid_init, pid_update

__all__ = ["PID", "PIDState", "pid_init", "pid_update"]
