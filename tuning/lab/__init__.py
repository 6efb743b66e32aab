"""The lab, end to end: ``run_lab`` writes the whole pre-lab and lab report (``jaxcart lab``).

Modules: :mod:`~tuning.lab.report` (the run and its outputs), :mod:`~tuning.lab.inputs` (which
recording is which part), :mod:`~tuning.lab.prelab` (appendix constants, the k_i bound),
:mod:`~tuning.lab.part_i` to :mod:`~tuning.lab.part_v` (Parts (i) to (v): each a ``compute``
returning a frozen result from explicit inputs, and a ``render`` that writes its section from
it), :mod:`~tuning.lab.model` (the cart model passed between parts, the one call of the plant
builder), :mod:`~tuning.lab.fits` (the swappable fitter), :mod:`~tuning.lab.deadband` (the
Coulomb dead band of Part (iii) as a finite, encoder-read run meets it), :mod:`~tuning.lab.data`
(the built-in example recordings), :mod:`~tuning.lab.figures` and :mod:`~tuning.lab.html`
(figures, Markdown/HTML). The report is written into a hidden staging folder and renamed into
place when complete (:func:`~tuning.lab.report.staged`).
"""

from tuning.lab.data import TRUE, builtin_dir, generate
from tuning.lab.inputs import SLOTS, find_inputs
from tuning.lab.prelab import ki_bound_locus, ki_bound_routh
from tuning.lab.report import run_lab

__all__ = [
    "TRUE",
    "builtin_dir",
    "generate",
    "SLOTS",
    "find_inputs",
    "ki_bound_locus",
    "ki_bound_routh",
    "run_lab",
]
