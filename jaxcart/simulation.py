"""One entry point for every simulator, which is a value (the way diffrax's ``diffeqsolve``
takes a solver): ``simulate(plant, controller, experiment, solver=Smooth())``.

- :class:`Smooth`: the smooth simulator (:mod:`jaxcart.smooth_sim`), pure JAX: ``jax.jit``,
  ``jax.vmap`` over gains or plant parameters, ``jax.grad``.
- :class:`Exact`: the exact simulator (:mod:`jaxcart.exact`), numpy float64, hard clip and
  event-exact stick-slip: the reference the smooth one converges to.
- :class:`Chunked`: the smooth loop in compiled chunks with progress on stderr
  (:mod:`jaxcart.chunked_sim`), for runs of millions of samples.

Every solver runs the same compatibility checks first (:func:`jaxcart.runcheck.check_run`)
and raises the one error type :class:`jaxcart.runcheck.IncompatibleRun`.

>>> import jaxcart as jc
>>> plant, pid, exp = jc.handout_plant(v_sat=6.0), jc.PID(kp=40.0, kd=4.0), jc.step(0.3)
>>> smooth = simulate(plant, pid, exp, solver=Smooth(smoothing=jc.EXACT_FORMS))
>>> exact = simulate(plant, pid, exp, solver=Exact())
>>> bool(abs(smooth.position - exact.position).max() < 1e-4)  # [m]; float64: < 1e-9
True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from jaxcart.chunked_sim import simulate_chunked
from jaxcart.exact import simulate_exact
from jaxcart.runcheck import IncompatibleRun, check_run
from jaxcart.smooth_sim import Response, simulate_smooth
from jaxcart.smoothing import Smoothing


class Solver(Protocol):
    """What :func:`simulate` takes: ``run(plant, controller, experiment) -> Response``."""

    def run(self, plant, controller, experiment) -> Response: ...


@dataclass(frozen=True)
class Smooth:
    """The smooth simulator. smoothing: widths of the smoothed nonlinearities (None: the
    default :class:`jaxcart.Smoothing`; ``jaxcart.EXACT_FORMS`` for hard clip); substeps:
    sub-steps per sample (None: :func:`jaxcart.substeps.substeps_per_sample`)."""

    smoothing: Smoothing | None = None
    substeps: int | None = None

    def run(self, plant, controller, experiment) -> Response:
        return simulate_smooth(
            plant, controller, experiment, smoothing=self.smoothing, substeps=self.substeps
        )


@dataclass(frozen=True)
class Exact:
    """The exact simulator (numpy float64; not traceable by JAX)."""

    def run(self, plant, controller, experiment) -> Response:
        return simulate_exact(plant, controller, experiment)


@dataclass(frozen=True)
class Chunked:
    """The smooth loop in chunks of ``chunk`` samples (None: :data:`jaxcart.chunked_sim.CHUNK`)
    with progress and the announced cost on ``out`` (None: stderr); ``n_columns``: columns of
    the CSV that will be written, for the announced cost. Numpy arrays in the response."""

    chunk: int | None = None
    n_columns: int = 5
    out: object = None

    def run(self, plant, controller, experiment) -> Response:
        return simulate_chunked(
            plant, controller, experiment, chunk=self.chunk, n_columns=self.n_columns, out=self.out
        )


def simulate(
    plant,
    controller,
    experiment,
    *,
    solver: Solver | None = None,
    smoothing: Smoothing | None = None,
    substeps: int | None = None,
) -> Response:
    """Simulate one experiment; returns a :class:`jaxcart.Response`.

    plant: :class:`jaxcart.Plant` (with its effects); controller: :class:`jaxcart.PID` (may be
    None for tap and open-loop experiments); experiment: :class:`jaxcart.Experiment`. solver:
    :class:`Smooth` (default), :class:`Exact` or :class:`Chunked`. ``smoothing`` and
    ``substeps`` are shorthand for ``solver=Smooth(smoothing, substeps)``.
    Raises :class:`jaxcart.runcheck.IncompatibleRun` when the three cannot run together.
    """
    if solver is None:
        solver = Smooth(smoothing=smoothing, substeps=substeps)
    elif smoothing is not None or substeps is not None:
        raise IncompatibleRun(
            f"simulate: smoothing and substeps belong to the solver; give "
            f"solver=Smooth(smoothing=..., substeps=...) instead of {type(solver).__name__}()"
        )
    if not hasattr(solver, "run"):
        raise IncompatibleRun(
            f"simulate: solver={solver!r}; give jaxcart.Smooth(), jaxcart.Exact() or "
            "jaxcart.Chunked()"
        )
    check_run(plant, controller, experiment)
    return solver.run(plant, controller, experiment)
