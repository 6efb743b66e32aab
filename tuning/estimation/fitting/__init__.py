"""The parts of ``jaxcart fit`` (:mod:`tuning.estimation.fit`, its public entry), by concern:
:mod:`.names` (parameter names, internal coordinates, plants with values), :mod:`.model` (theta's
layout and the smooth and exact residuals), :mod:`.result` (the result types and their JSON),
:mod:`.files` (the fitted plant file), :mod:`.plot` (the overlay plot)."""
