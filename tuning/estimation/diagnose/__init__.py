"""Diagnosis of recordings against the model: where they part, which physics was left out,
the model with it, and the fit improving (``jaxcart diagnose``; docs/diagnose.md).

    d = diagnose([read_experiment("run.toml")])     # a Diagnosis (compute only)
    print(render_markdown(d)); plot_diagnosis(d, "diagnosis.png"); d.to_json()
"""

from tuning.estimation.diagnose.report import plot_diagnosis, render_markdown, write_outputs
from tuning.estimation.diagnose.result import Diagnosis
from tuning.estimation.diagnose.search import diagnose

__all__ = ["Diagnosis", "diagnose", "plot_diagnosis", "render_markdown", "write_outputs"]
