"""The structures a diagnosis compares: which parts (effects, parameter corrections, the drive
limits free per run) each holds, which parameters it frees, and how the search makes them (round
1's singles, pairs, forward selection's additions, a part taken away)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from jaxcart.effects import REGISTRY
from tuning.estimation.diagnose.policy import K_MAX, PER_ROUND
from tuning.estimation.engine import parameters

#: The parameter corrections a structure may hold, and the parameter each frees: the cart's mass
#: [kg], the drive's gain (a scale on the handout's force per volt).
PARAM_ERRORS = {"mass": ("M",), "gain": ("gamma_scale",)}
#: The part that frees the drive per recording: on several runs of one cart each run has its
#: own amplifier limit (the motor warms, the supply sags), and with the gain corrected its own
#: gain; the mechanics are shared.
PER_RUN = "per_run"


def effect_params() -> dict:
    """Effects a candidate adds, and the parameters it frees (B_eq is always free): every
    registered effect that is a candidate (``Effect.not_candidate``), as registered now."""
    return parameters.candidates()


def not_candidates() -> dict:
    """Registered effects that are not candidates, and why (each effect declares it)."""
    return {n: cls.not_candidate for n, cls in REGISTRY.items() if cls.not_candidate}


def limit_params() -> tuple:
    """The parameters of the effects that limit the drive (``Effect.limits``)."""
    return tuple(p.name for n in effect_params() if REGISTRY[n].limits for p in REGISTRY[n].params)


def per_run_params() -> tuple:
    """The parameters a PER_RUN structure frees per recording: its drive limits, and the
    drive's gain where it corrects the gain (:meth:`~.search.Search.gain_per_run`)."""
    return (*limit_params(), *PARAM_ERRORS["gain"])


def motor_only() -> set:
    """Parts that act only with the motor connected: effects of the drive alone, and the
    parameter corrections (a tap cannot tell M from B_eq)."""
    return {n for n in effect_params() if REGISTRY[n].drive_only()} | set(PARAM_ERRORS)


@dataclass
class Candidate:
    """One structure of a diagnosis (its parts and free parameters) and what the search found
    for it: values, smooth and exact RMS [m], score, residuals, Jacobian, significance."""

    name: str
    parts: tuple  # effect or parameter-error names (and PER_RUN)
    free: tuple  # free parameter names (``name@i``: recording i's own value)
    values: dict = field(default_factory=dict)
    rms_smooth: float = math.nan
    rms_exact: float = math.nan
    score: float = math.nan
    window_evidence: float = math.nan
    residuals: list = field(default_factory=list)
    jac: object = None
    scale: float = 1.0
    round: int = 1
    #: Significance of each named effect or correction (z,
    #: :func:`~.significance.significance`) and why the structure is not eligible ("" when
    #: every part is significant), at ``assessed`` values.
    z: dict = field(default_factory=dict)
    why: dict = field(default_factory=dict)
    #: The parts whose every item is idle at ``assessed`` values (a correction within its
    #: margin, an effect under its least size: :func:`~.significance.significance`).
    idle: tuple = ()
    assessed: object = None
    #: The values (:func:`values_key`) an exact polish converged at: one from them would
    #: repeat itself, so it is not run again.
    settled: object = None
    #: the recordings a PER_RUN part frees the drive limits of (driven runs)
    runs: tuple = ()
    #: (values key, the exact Jacobian there) of the held-out re-fits (crossval.exact_jacobian)
    jac_exact: tuple = (None, None)
    #: {"residuals": each recording's held-out prediction [m], "score"} at ``held_out_key``
    held: dict = field(default_factory=dict)
    held_out_key: object = None
    #: Its fit as every fit reports one (a :class:`~tuning.estimation.fitting.result.FitResult`:
    #: values with standard errors, each recording's runs, the fitted cart), made when the
    #: search ends (:func:`~.verdict.diagnosis`); None before.
    result: object = None

    @property
    def why_not(self) -> str:
        return "; ".join(f"{k}: {v}" for k, v in self.why.items() if v)

    @property
    def effects(self) -> tuple:
        out = []
        for p in self.parts:
            if p in effect_params():
                out += list(parameters.named_by(p))
        return tuple(dict.fromkeys(out))

    @property
    def corrections(self) -> tuple:
        return tuple(p for p in self.parts if p in PARAM_ERRORS)

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "effects": list(self.effects),
            "parameter_corrections": [PARAM_ERRORS[p][0] for p in self.corrections],
            "free": list(self.free),
            "rms_smooth": self.rms_smooth,
            "rms": self.rms_exact,
            "score": self.score,
            "round": self.round,
            "fit": None if self.result is None else self.result.to_json(),
            "significance": dict(self.z),
            "eligible": self.assessed is not None and not self.why_not,
            "why_not": self.why_not,
            "window_evidence": self.window_evidence,
            "values": {k: v for k, v in self.values.items() if "@" not in k},
            "per_recording": {
                k: v
                for k, v in self.values.items()
                if parameters.base_name(k) in per_run_params() and "@" in k
            },
        }


def candidate_list(motor: bool, runs=(), coverage=None) -> list[Candidate]:
    """Round 1: the baseline, each correction and effect alone, and with two runs or more of
    a driven cart (``runs``: their recording indices) each drive limit free per run; an effect
    only where the recordings meet its data conditions (``coverage``, a
    :class:`~tuning.estimation.engine.coverage.Coverage`; None: every effect)."""
    out = [Candidate("baseline", (), ("B_eq",))]
    names = list(PARAM_ERRORS) + list(effect_params())
    for n in names:
        if n in motor_only() and not motor:
            continue
        if coverage is not None and n in REGISTRY and coverage.lacks(REGISTRY[n]):
            continue
        out.append(structure((n,), runs))
    if len(runs) >= 2:
        out += [structure((n, PER_RUN), runs) for n in effect_params() if REGISTRY[n].limits]
    return out


def pair(a: Candidate, b: Candidate) -> Candidate:
    return structure(tuple(dict.fromkeys(a.parts + b.parts)), a.runs or b.runs)


def structure(parts, runs=()) -> Candidate:
    """The candidate of ``parts``: B_eq and each part's parameters free; with :data:`PER_RUN`
    among them, each drive limit's value (and the drive's gain, where corrected) free per run
    of ``runs`` instead of shared."""
    free = ["B_eq"]
    for p in parts:
        free += list(effect_params().get(p) or PARAM_ERRORS.get(p, ()))
    if PER_RUN in parts:
        free = [
            x for n in free for x in ([f"{n}@{i}" for i in runs] if n in per_run_params() else [n])
        ]
    return Candidate("+".join(parts), tuple(parts), tuple(dict.fromkeys(free)), runs=tuple(runs))


def without_part(parts, part) -> tuple:
    """``parts`` without ``part``, keeping what it stands on (``Effect.requires``): Stribeck
    friction without its fall is stiction, not the baseline."""
    rest = [p for p in parts if p != part]
    for r in REGISTRY[part].requires if part in REGISTRY else ():
        standing = rest + [x for x in REGISTRY[part].requires if x != r]
        if r not in rest and not any(r in REGISTRY[q].requires for q in standing if q in REGISTRY):
            rest.append(r)
    return tuple(rest)


def extend(seeds, additions, seen, kmax=K_MAX, limit=PER_ROUND) -> list:
    """Forward selection: each seed structure with one more addition (a single structure),
    at most ``kmax`` free parameters (the batch's slots) and one parameter correction, not in
    ``seen`` (sets of parts; updated), Coulomb and stiction not both (stiction holds Coulomb),
    at most ``limit`` of them, by the sum of the seed's and the addition's ranks (the best
    seed first among equals). Returns [(candidate, seed, addition)]."""
    ranked = sorted(
        ((i + j, i, a, b) for i, a in enumerate(seeds) for j, b in enumerate(additions)),
        key=lambda t: t[:2],
    )
    out = []
    for _, _, a, b in ranked:
        c = pair(a, b)
        parts = frozenset(c.parts)
        if (
            parts in seen
            or len(c.parts) == len(a.parts)
            or len(c.free) > kmax
            or not batchable(parts)
        ):
            continue
        seen.add(parts)
        out.append((c, a, b))
        if len(out) >= limit:
            break
    return out


def batchable(parts) -> bool:
    """Whether a structure of ``parts`` is one the batch fits: no two parts that do one job
    (:func:`~tuning.estimation.engine.parameters.redundant`), one parameter correction at
    most, and not the drive's gain with the drive free per run (that one is
    :meth:`~.search.Search.gain_per_run`'s alone: the batch's layout has no gain per run)."""
    parts = frozenset(parts)
    return (
        not parameters.redundant(parts)
        and len([p for p in parts if p in PARAM_ERRORS]) <= 1
        and not {"gain", PER_RUN} <= parts
    )


def pair_starts(grown, starts_all, base) -> list:
    """Start values of combined structures: the seed's fitted values over the addition's over
    the defaults. A structure that scores worse than the ``base``line it nests has not fitted
    (the real P 50 run: Coulomb alone ends at f_c 2.9 N and 9.9 mm, the baseline at 8.2 mm),
    and its values are not a start (from them saturation + Coulomb stays at 9.9 mm; from the
    saturation's values and f_c's start it reaches 1.19 mm)."""
    starts = []
    for c, a, b in grown:
        s = {k: starts_all[parameters.base_name(k)] for k in c.free}
        for fitted in (b, a):
            if fitted.score <= base.score:
                s.update({k: v for k, v in fitted.values.items() if k in c.free})
        starts.append(s)
    return starts


def params_of(cand) -> set:
    """The base names of the parameters ``cand`` frees."""
    return {parameters.base_name(n) for n in cand.free}


def swapped_correction(parts, values, plant):
    """The structure with the other of M and gamma_scale, and the values that give the same
    motion: the cart obeys y'' + (c/m) y' = (gamma/m) v + F/m, so with B_eq free a closed loop
    fixes only gamma/m, c/m and every force over m (c = B_eq + B_emf, m = M + M_J, B_emf and
    M_J from the motor's constants). Returns (parts, values) or None (one correction needed;
    None also when the equivalent B_eq or M is not positive: then the two differ)."""
    corr = [p for p in parts if p in PARAM_ERRORS]
    if PER_RUN in parts or len(corr) != 1 or not plant.motor_connected:
        return None  # (with the drive free per run, each run's gain is its own)
    m_j, b_emf = float(plant.M_J), float(plant.B_emf)
    m0, g0 = float(plant.M), float(plant.gamma_scale)
    new = {k: v for k, v in values.items() if k not in ("M", "gamma_scale")}
    if corr[0] == "mass":
        k = (m0 + m_j) / (values["M"] + m_j)  # m_new / m_old
        new["gamma_scale"] = g0 * k
        swap = "gain"
    else:
        k = g0 / values["gamma_scale"]
        new["M"] = (m0 + m_j) * k - m_j
        swap = "mass"
        if new["M"] <= 0:
            return None
    new["B_eq"] = (values["B_eq"] + b_emf) * k - b_emf
    if new["B_eq"] <= 0:
        return None
    for n in ("f_c", "f_s", "k_s"):
        if n in new:
            new[n] = values[n] * k
    return tuple(swap if p == corr[0] else p for p in parts), new
