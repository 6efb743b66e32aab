"""The diagnosis's policy in one place: the criterion's penalties, the smoothing widths and
iterations of the search's rounds, its slots and sizes, and the thresholds of significance,
plausibility and drive limits per run. Each constant says why it has its value."""

from __future__ import annotations

from tuning.estimation.engine import parameters

#: Information criterion: penalty per free parameter (times log n_eff) and per added effect.
PENALTY_PER_PARAM = 1.0
PENALTY_PER_EFFECT = 12.0
#: Near-ties: another structure within this many criterion units of the best is named too.
TIE = 6.0
#: The smoothing widths of round 1's continuation (times each effect's own), widest first.
WIDTHS = (4.0, 1.0, 0.3, 0.1)
#: ... and of the later rounds, which start from fitted values: at the widest the dry friction
#: they fitted is smoothed into another model, and its steps are spent walking away (the real
#: P 50 run's saturation + Coulomb + mass, 1.17 mm at the narrowest, is 2.04 mm at 4x).
LATER_WIDTHS = WIDTHS[1:]
#: Round 1 is also fitted straight from the start at narrow widths: the continuation can lead
#: astray where a wide width changes the physics (static friction smoothed wide is a larger
#: Coulomb friction, and a ramp that breaks away late fits B_eq at its bound with f_c = 0;
#: from the start at these widths it finds the truth).
DIRECT_WIDTHS = (0.01, 0.001)
ITERATIONS = (8, 8, 8, 8)
MIN_SAMPLES = 200
#: A tap's coasting part shorter than this many samples is not diagnosed.
MIN_COASTING = 50
#: Free slots of every candidate (B_eq + two effects' parameters), so one compile serves all.
K_MAX = 5
#: An exact polish weighs each recording by its own misfit at its start, and again at the
#: values it reached while the weights move by more than this share, at most REWEIGHTS times.
REWEIGHT = 0.2
REWEIGHTS = 4
#: A structure richer than the lead by one value is re-fitted from the lead's values with that
#: value at this many points over its plausible range (and its own).
SPREAD = 3
#: Structures polished on the exact simulator (the best by score after the smooth fits).
POLISH = 4
#: Structures re-fitted from the best-scoring one's values after the search, besides those
#: nested in it (the best by score).
NESTED = 8
#: Such a re-fit stops after its first Jacobian where the linearised fit cannot come within
#: this factor of the cost [m^2] at which the structure would tie with the best (the exact
#: model is piecewise smooth: its linearisation may miss a basin by far less than this).
SCREEN = 4.0
MIN_COUNTS = 20
#: A drive's limit changes from run to run with the supply and the motor's temperature by tens
#: of percent; a run's own limit this many times below what another run of the same drive
#: demonstrably drew is more than one drive's spread
#: (:func:`~.per_run.per_run_inconsistency`): such a structure does not seed the forward
#: selection (grown, it takes the slots other effects need), and where held-out prediction
#: names it the verdict says so. On the lab's
#: real runs, a PD run held back early in its travel fits a current limit of 0.68 A where the
#: P 50 runs drew 1.5-2.3 A (2.3-3.4 times).
RUN_SPREAD = 2.0
#: The drive limits free per run are named only when two runs' values differ by more than this
#: many standard errors (a Wald test: z > 3 leaves a chance of about 1e-3 that noise alone put
#: them apart); an effect's or a correction's z (see :func:`~.significance.significance` for
#: each strength and neutral value) is reported, its place decided by held-out prediction.
SIGNIFICANCE = 3.0
#: A parameter correction is named only when it exceeds this share of the start plant's value
#: (an equivalence margin: the appendix gives M to two digits,
#: 0.94 kg; a controller that reads whole encoder counts, which the simulation does not model,
#: moves a fitted M by 0.02-0.15 % on recordings with no mass error, a true error is 10 % and
#: more).
CORRECTION_MARGIN = 0.01
#: A fitted value within this relative distance of a bound of :data:`~batch.BOUNDS` (a share
#: of the range for a parameter not fitted as a logarithm) sits at that bound.
AT_BOUND = 1e-2
#: Ranges of the plant's own parameters a real cart of this lab has (declared with them,
#: jaxcart.plantspec): the fits are held inside them; a value at their edge is flagged.
PLAUSIBLE = {n: parameters.spec(n).plausible for n in parameters.CORRECTABLE}
#: Forward selection (round 3 on): the best structures of the last round extended, and at
#: most this many new structures per round (the batch keeps round 1's shape: no new compile).
SEEDS = 3
PER_ROUND = 6
