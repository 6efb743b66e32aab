"""The one estimation engine that ``jaxcart fit``, ``jaxcart diagnose`` and the lab share.

- :mod:`.parameters`: every fitted parameter's transform, bounds, neutral value and role,
  derived from the effects registry (``jaxcart.effects``) and the plant's own declarations;
  names of the form ``name@i`` are per-recording copies (recording ``i``), ``name[k]`` the
  elements of a vector parameter.
- :mod:`.segments`: the one :class:`~.segments.Segment` and :func:`~.segments.prepare` (a
  recording as the part fitted: a tap's coasting part, every position the middle of its count).
- :mod:`.noise`: the encoder count, the noise floor, the effective number of samples, and the
  widening of standard errors for model error.
- :mod:`.lm`: the damped least-squares (Levenberg-Marquardt) step.
- :mod:`.batch`: candidates x recordings in one compiled, sharded Levenberg-Marquardt loop,
  with parameters shared across recordings or free per recording.
- :mod:`.exact_polish`: Gauss-Newton on the exact simulator's residuals
  (:func:`~.exact_polish.polish`), the last step of ``fit`` and of ``diagnose``'s exact re-fits.
- :mod:`.exact_runs`: one recording's exact run as a job for a helper process
  (:mod:`jaxcart.workers`), so that a re-fit makes its runs several at a time.
- :mod:`.covariance`: robust (run-clustered sandwich with the encoder floor) and naive
  covariances, with the directions the data do not determine flagged; the one
  :class:`~.covariance.Covariance` both report.
"""
