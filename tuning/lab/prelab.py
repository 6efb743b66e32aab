"""Pre-lab arithmetic: the appendix's derived constants and the PI stability bound on k_i.

With P gain k and integral gain k_i on the cart m y'' + c y' = gamma v, the closed loop has the
characteristic polynomial

    m s^3 + c s^2 + gamma k s + gamma k_i

Routh: the first column m, c, (c gamma k - m gamma k_i)/c, gamma k_i is positive iff
0 < k_i < c k / m. The same bound is where the root locus of

    H(s) = gamma / (m s^3 + c s^2 + gamma k s)      (gain k_i)

crosses the imaginary axis, at s = +/- j sqrt(gamma k / m); :func:`ki_bound_locus` finds that
crossing numerically from python-control's closed-loop poles, independently of the formula.

>>> round(ki_bound_routh(1.0731, 13.1236, 10.0), 2)
122.3
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import control
import numpy as np
from scipy.optimize import brentq

import jaxcart as jc
from jaxcart.exact import simulate_exact, step_info_exact
from jaxcart.metrics import SETTLING_BAND
from jaxcart.params import Plant
from jaxcart.plots import Run, plot_runs, reference_run
from tuning.design.tune import tune
from tuning.lab import figures
from tuning.lab.context import value


def appendix(plant: Plant | None = None) -> dict:
    """Derived constants of the appendix: M, M_J, m [kg], B_emf [kg/s], gamma [N/V]."""
    plant = Plant() if plant is None else plant
    return {
        "M": float(plant.M),
        "M_J": float(plant.M_J),
        "m": float(plant.m),
        "B_emf": float(plant.B_emf),
        "gamma": float(plant.gamma),
    }


def ki_bound_routh(m: float, c: float, k: float) -> float:
    """Largest stable integral gain k_i [V/(m s)] from the Routh condition: c k / m.

    m: moving mass [kg]; c: total damping B_eq + B_emf [kg/s]; k: P gain [V/m].
    """
    return c * k / m


def open_loop(m: float, c: float, gamma: float, k: float):
    """H(s) = gamma / (m s^3 + c s^2 + gamma k s): the loop seen by k_i (python-control tf)."""
    return control.tf([gamma], [m, c, gamma * k, 0.0])


def closed_loop_poles(m, c, gamma, k, ki) -> np.ndarray:
    """Poles of the PI loop with gain k_i, from python-control's feedback(k_i H, 1)."""
    return np.asarray(control.feedback(ki * open_loop(m, c, gamma, k), 1).poles())


def ki_bound_locus(m: float, c: float, gamma: float, k: float) -> tuple[float, float]:
    """(k_i, omega): where the root locus of H crosses the imaginary axis, found numerically.

    Bisects on the largest real part of the closed-loop poles (python-control), so it does not
    use the Routh formula. omega [rad/s] is the crossing frequency.
    """

    def growth(ki):
        return float(np.max(closed_loop_poles(m, c, gamma, k, ki).real))

    lo, hi = 1e-6, 1.0
    while growth(hi) < 0:
        lo, hi = hi, hi * 4.0
        if hi > 1e12:
            raise ValueError("the root locus never crosses the imaginary axis")
    ki = brentq(growth, lo, hi, xtol=1e-14, rtol=1e-14, maxiter=500)
    poles = closed_loop_poles(m, c, gamma, k, ki)
    omega = float(np.max(np.abs(poles.imag)))
    return float(ki), omega


def locus_data(m, c, gamma, k, ki_max):
    """Root locus of H for k_i in [0, 3 ki_max] (python-control's root_locus_map)."""
    gains = np.concatenate([[0.0], np.geomspace(1e-3, 3.0 * ki_max, 600)])
    gains = np.sort(np.concatenate([gains, [ki_max]]))
    return control.root_locus_map(open_loop(m, c, gamma, k), gains=gains)


# ---------------------------------------------------------------- the PI bound as a result

#: The handout's P gain for the PI analysis [V/m] and its B_eq estimate [kg/s].
K_PI = 10.0
B_EQ_HANDOUT = 5.4


@dataclass(frozen=True)
class KiBound:
    """The largest stable k_i of the PI loop on m s³ + c s² + γ k s + γ k_i, two ways.

    m [kg], c [kg/s], gamma [N/V], k [V/m]; ki_routh, ki_locus [V/(m s)]; omega [rad/s]: the
    imaginary-axis crossing; relative: |ki_locus - ki_routh| / ki_routh; poles [1/s]: the
    closed-loop poles at the Routh bound; locus: python-control's root-locus map (figure).
    """

    m: float
    c: float
    gamma: float
    k: float
    ki_routh: float
    ki_locus: float
    omega: float
    relative: float
    poles: tuple
    locus: object = field(repr=False, compare=False)

    def to_json(self) -> dict:
        return {
            "k": self.k,
            "m": self.m,
            "c": self.c,
            "gamma": self.gamma,
            "ki_max_routh": self.ki_routh,
            "ki_max_locus": self.ki_locus,
            "crossing_omega": self.omega,
            "relative_difference": self.relative,
            "poles_at_bound": [[p.real, p.imag] for p in map(clean_pole, self.poles)],
        }

    def values(self, key: str, part: str) -> list:
        return [
            value(
                f"{key}_routh",
                self.ki_routh,
                "V/(m s)",
                f"largest stable k_i, Routh ({part})",
                part,
            ),
            value(
                f"{key}_locus",
                self.ki_locus,
                "V/(m s)",
                f"largest stable k_i, root-locus crossing ({part})",
                part,
            ),
        ]


def ki_bound(m: float, c: float, gamma: float, k: float) -> KiBound:
    """The Routh bound and the root-locus crossing of the PI loop (see :class:`KiBound`)."""
    ki_routh = ki_bound_routh(m, c, k)
    ki_locus, omega = ki_bound_locus(m, c, gamma, k)
    poles = closed_loop_poles(m, c, gamma, k, ki_routh)
    return KiBound(
        m,
        c,
        gamma,
        k,
        ki_routh,
        ki_locus,
        omega,
        abs(ki_locus - ki_routh) / ki_routh,
        tuple(complex(p) for p in poles),
        locus_data(m, c, gamma, k, ki_routh),
    )


def render_ki_bound(lab, bound: KiBound, *, name: str, title: str) -> None:
    """The bound's paragraph and root-locus figure ``name``."""
    m, c, gamma, k = bound.m, bound.c, bound.gamma, bound.k
    path, rel_path = lab.figure_path(name)
    figures.root_locus(path, bound.locus, ki_bound=bound.ki_locus, omega=bound.omega, title=title)
    pole_text = ", ".join(_pole(p) for p in sorted(bound.poles, key=lambda p: (p.real, p.imag)))
    lab.doc.paragraph(
        f"Characteristic polynomial m s³ + c s² + γ k s + γ k_i with m = {m:.4f} kg, "
        f"c = {c:.4f} kg/s, γ = {gamma:.4f} N/V, k = {k:g} V/m. Routh's first column "
        f"(m, c, γ (c k − m k_i)/c, γ k_i) stays positive for 0 < k_i < c k / m = "
        f"**{bound.ki_routh:.4f} V/(m s)**. The root locus of H(s) = γ / (m s³ + c s² + γ k s) "
        f"(python-control) crosses the imaginary axis at k_i = {bound.ki_locus:.4f} V/(m s), "
        f"s = ±j {bound.omega:.4f} rad/s (found by bisection on the closed-loop poles; relative "
        f"difference from Routh {bound.relative:.1e}; √(γ k / m) = "
        f"{math.sqrt(gamma * k / m):.4f} rad/s). Closed-loop poles at the bound: {pole_text}."
    )
    lab.doc.figure(
        rel_path,
        f"Root locus of H(s) with gain k_i (k = {k:g} V/m, c = {c:.3f} "
        f"kg/s); the imaginary-axis crossing is marked.",
    )


def clean_pole(p, rel: float = 1e-9) -> complex:
    """A pole with the round-off of its real or imaginary part (below ``rel`` of |p|) set to 0."""
    p = complex(p)
    tiny = rel * max(1.0, abs(p))
    return complex(0.0 if abs(p.real) < tiny else p.real, 0.0 if abs(p.imag) < tiny else p.imag)


def _pole(p) -> str:
    p = clean_pole(p)
    sign = "+" if p.imag > 0 else "−"
    if p.imag == 0:
        return f"{p.real:.4f}"
    if p.real == 0:
        return f"{sign}j{abs(p.imag):.4f}"
    return f"{p.real:.4f} {sign} j{abs(p.imag):.4f}"


def gains_on_bounds(result) -> dict:
    """{name: (side, bound)} for each tuned parameter on, or within 1 % of, the tuner's box
    (side "upper" or "lower"), as :func:`tuning.design.tune.tune` flags it."""
    return {n: (str(v[0]), float(v[1])) for n, v in (result.on_bound or {}).items()}


# ---------------------------------------------------------------- the pre-lab: compute


@dataclass(frozen=True)
class Prelab:
    """The pre-lab's answers: the appendix constants (:func:`appendix`), the PI bound on the
    handout's model, and the PID tuned on it with its exact step response (0.5 m, 3 s) and
    metrics; ``tuned``: the :class:`tuning.design.result.TuneResult`."""

    appendix: dict
    bound: KiBound
    tuned: object
    response: object = field(repr=False)
    info: object = None

    @property
    def gains(self):
        """The tuned PID (:class:`jaxcart.PID`)."""
        return self.tuned.gains

    @property
    def on_bounds(self) -> dict:
        return gains_on_bounds(self.tuned)


def compute(*, say=lambda text: None) -> Prelab:
    """The pre-lab on the handout's model: constants, the k_i bound at k = 10 V/m, a tuned PID."""
    say("pre-lab: appendix constants, Routh bound and root locus")
    a = appendix(jc.Plant())
    bound = ki_bound(a["m"], B_EQ_HANDOUT + a["B_emf"], a["gamma"], K_PI)
    say("pre-lab: tuning the PID on the handout's model (as jaxcart tune does)")
    plant = jc.handout_plant()
    res = tune(plant, progress=False)  # the settings of jaxcart tune: one tuner, one answer
    exp = jc.step(0.5, horizon=3.0)
    info = step_info_exact(plant, res.gains, exp)
    result = Prelab(a, bound, res, simulate_exact(plant, res.gains, exp), info)
    g = res.gains
    say(
        f"pre-lab: tuned kp = {g.kp:.4g}, kd = {g.kd:.4g}, ki = {g.ki:.4g}: settling "
        f"{info.settling_time:.3f} s, overshoot {info.overshoot:.2f} %"
    )
    return result


def values(p: Prelab) -> list:
    a, g, info = p.appendix, p.gains, p.info
    out = [
        value("gamma", a["gamma"], "N/V", "γ, force per volt (appendix)", "pre-lab"),
        value("m", a["m"], "kg", "m = M + M_J (appendix)", "pre-lab"),
        value("B_emf", a["B_emf"], "kg/s", "B_emf, back-EMF damping (appendix)", "pre-lab"),
        *p.bound.values("ki_max_prelab", "pre-lab"),
    ]
    out += [
        value(f"pid_{n}", float(getattr(g, n)), u, f"tuned PID {n}", "pre-lab")
        for n, u in (("kp", "V/m"), ("kd", "V s/m"), ("ki", "V/(m s)"))
    ]
    for name, unit, what in (
        ("rise_time", "s", "rise time"),
        ("overshoot", "%", "overshoot"),
        ("settling_time", "s", "settling time"),
        ("steady_state_error", "m", "steady-state error"),
    ):
        label = f"tuned PID {what} (handout model)"
        out.append(value(f"pid_{name}", getattr(info, name), unit, label, "pre-lab"))
    return out


def to_json(p: Prelab) -> dict:
    return {
        "appendix": p.appendix,
        "pi_bound": p.bound.to_json(),
        "pid": {
            "gains": p.gains.to_dict(),
            "metrics": p.info.as_dict(),
            "meets": p.info.meets(),
            "tune_seconds": p.tuned.seconds,
            "tune_message": p.tuned.message,
            "on_bounds": {n: {"side": s, "bound": b} for n, (s, b) in p.on_bounds.items()},
            "bounds": {n: list(b) for n, b in p.tuned.bounds.items()},
            "binding": p.tuned.binding,
        },
    }


# ---------------------------------------------------------------- the pre-lab: render


def render(lab, p: Prelab) -> None:
    """The pre-lab's section of the report."""
    doc, a = lab.doc, p.appendix
    doc.heading("Pre-lab")
    doc.paragraph(
        "Constants from the appendix (Rm = 2.6 Ω, Kt = Km = 0.00767, Jm = 3.9e-7 kg m², "
        "Kg = 3.71, r_mp = 6.35 mm, η = 1, M = Mc + Mw = 0.57 + 0.37 kg):"
    )
    doc.table(
        ["quantity", "formula", "value", "unit"],
        [
            ["M_J", "η_g Kg² Jm / r_mp²", f"{a['M_J']:.4f}", "kg"],
            ["m", "M + M_J", f"{a['m']:.4f}", "kg"],
            ["B_emf", "η_g Kg² η_m Kt Km / (Rm r_mp²)", f"{a['B_emf']:.4f}", "kg/s"],
            ["γ", "η_g Kg η_m Kt / (Rm r_mp)", f"{a['gamma']:.4f}", "N/V"],
        ],
        numeric=[False, False, True, False],
    )
    doc.heading("Largest stable k_i (k = 10 V/m, B_eq = 5.4 kg/s)", 3)
    render_ki_bound(
        lab,
        p.bound,
        name="prelab_root_locus",
        title="Pre-lab: root locus of γ/(m s³ + c s² + γ k s), k = 10 V/m, B_eq = 5.4 kg/s",
    )
    doc.heading("PID design (jaxcart tune)", 3)
    _render_design(lab, p)


def _render_design(lab, p: Prelab) -> None:
    doc, g, res, info, response = lab.doc, p.gains, p.tuned, p.info, p.response
    path, rel = lab.figure_path("prelab_pid_step")
    plot_runs(
        [
            reference_run(response.time, response.reference),
            Run(
                "exact simulation, handout model, 6 V saturation",
                response.time,
                response.position,
                response.command,
            ),
        ],
        title=f"Pre-lab PID design: kp = {g.kp:.4g} V/m, kd = {g.kd:.4g} V s/m, "
        f"ki = {g.ki:.4g} V/(m s); step 0.5 m",
        path=path,
        v_limit=6.0,
        band=SETTLING_BAND,
        zoom=True,
    )
    message = res.message.strip().rstrip(".")
    message = message[:1].upper() + message[1:]
    doc.paragraph(
        "The design problem: move 0.5 m, 2 % settling time under 1 s, overshoot under 5 %, "
        "with the 6 V saturation, on the handout's model (B_eq = 5.4 kg/s). `jaxcart tune` "
        f"(gradient descent through the smooth simulator, {res.n_starts} starts, "
        f"{res.iterations} iterations, from the handout's kp = 40, kd = 5, ki = 5; the same "
        f"tuner with the same settings as here) found the gains below in {res.seconds:.1f} s; "
        f"the metrics are those of the exact simulator (hard clip, 1 ms digital loop). "
        f"{message}. What limits the gains: {res.binding}."
    )
    box = {n: v for n, v in p.on_bounds.items() if not (n in res.limits and v[0] == "upper")}
    if box:  # on an end of the box that the cart does not set
        doc.note(_on_bounds_note(g, box))
    rows = [
        ["kp", f"{g.kp:.4g}", "V/m"],
        ["kd", f"{g.kd:.4g}", "V s/m"],
        ["ki", f"{g.ki:.4g}", "V/(m s)"],
        ["tau (derivative filter)", f"{g.tau:g}", "s"],
        ["rise time (10-90 %)", f"{info.rise_time:.3f}", "s"],
        ["overshoot", f"{info.overshoot:.2f}", "%"],
        ["settling time (2 %)", f"{info.settling_time:.3f}", "s"],
        ["steady-state error at 3 s", mm_text(info.steady_state_error), "mm"],
        ["meets the design problem", "yes" if info.meets() else "no", ""],
    ]
    doc.table(["", "value", "unit"], rows, numeric=[False, True, False])
    doc.figure(
        rel,
        "Pre-lab: step response of the tuned PID (exact simulator, handout model "
        "with the 6 V saturation); voltage below, ±6 V limits dotted.",
    )


def _on_bounds_note(g, on_bounds: dict) -> str:
    units = {"kp": "V/m", "kd": "V s/m", "ki": "V/(m s)", "tau": "s"}
    listed = ", ".join(
        f"{n} = {float(getattr(g, n)):.4g} {units.get(n, '')} on its {side} bound "
        f"({b:g} {units.get(n, '')})".replace(" )", ")")
        for n, (side, b) in on_bounds.items()
    )
    return (
        f"The tuned gains sit on the tuner's search box: {listed}. This is the box's "
        f"answer, not the problem's: gains beyond it may do better on the model. "
        f"`jaxcart tune --bound NAME=LO,HI` widens the box."
    )


def mm_text(x) -> str:
    return f"{float(x) * 1e3:.3g}"
