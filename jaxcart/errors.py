"""Errors the user can fix: the command line prints them as one line, without a traceback."""


class UserError(ValueError):
    """Bad input (file, column, unit, value) with a message that says what to fix."""


class SimulationDiverged(UserError):
    """The simulated loop blew up (position not finite or beyond 1 km)."""
