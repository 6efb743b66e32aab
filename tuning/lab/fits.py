"""How the lab's parts fit parameters to recordings: one swappable function.

A part that fits takes ``fit`` as an argument (default :func:`fit`), so a report can hand the
parts another estimator (a joint fit over every recording, say) without touching them. Any
replacement takes the same arguments and returns an object with the
:class:`tuning.estimation.fit.FitResult` fields the parts read: ``params`` (name -> estimate
with ``value``, ``stderr``, ``identifiable``, ``note``), ``segments`` (``time``,
``after_exact``, ``nuisance``), ``rms_after_exact`` and ``to_json()``.
"""

from __future__ import annotations

from collections.abc import Callable

from tuning.estimation.fit import FitSettings
from tuning.estimation.fit import fit as engine_fit
from tuning.lab.context import fmt

#: fit(recordings, params, *, initial=None, settings=None) -> FitResult
FitFunction = Callable[..., object]


def fit(recordings, params, *, initial=None, settings=None, per_recording=(), executor=None):
    """Fit ``params`` (names) to ``recordings`` from ``initial`` (name -> value) with the
    estimation engine; ``settings``: a :class:`FitSettings` (default its continuation: a real
    tap needs it; :meth:`FitSettings.warm` where the start is close, an earlier part's values;
    :meth:`FitSettings.exact_only` at a neighbouring fit's answer);
    ``per_recording``: those of ``params`` free in each recording (the cart's joint fit);
    ``executor``: makes the exact runs (:func:`tuning.estimation.fit.fit`)."""
    return engine_fit(
        recordings,
        params,
        per_recording=per_recording,
        initial=initial,
        settings=settings or FitSettings(),
        progress=False,
        executor=executor,
    )


def estimate(result, name):
    """The fitted estimate of ``name``, or None when it is missing or not identifiable."""
    est = result.params.get(name)
    return None if est is None or not est.identifiable else est


def pm(est, unit, digits=5) -> str:
    """ "value ± stderr unit" for a table, or "not identifiable"; a value on an edge of the
    range the fit holds it in is said to be no estimate."""
    if est is None:
        return "not identifiable"
    text = f"{fmt(est.value, digits)} ± {fmt(est.stderr, 2)} {unit}"
    edge = getattr(est, "edge", None)
    if edge is not None:
        text += f" (at the {edge[0]} edge of its allowed range: no estimate)"
    return text
