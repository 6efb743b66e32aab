"""The friction curve a diagnosis read (:mod:`.friction_curve`) in its report: a section of
Markdown and a figure of the friction against the speed, each direction with its 90 % band,
beside the friction law of the named structure it competed with."""

from __future__ import annotations

import math

import numpy as np

from jaxcart import plots

#: The band drawn: +- this many standard errors (90 %, two-sided).
Z90 = 1.645


def curve_section(d, figure: str | None = None, plant_file: str | None = None) -> list:
    """Markdown lines: what the curve shows, whether it is named and why, the held-out table,
    the curve's values (empty when no curve was tried)."""
    fc = d.friction_curve
    if not fc:
        return []
    lines = ["", "## Friction as a curve of the speed", ""]
    if not fc.get("sides"):
        return lines + [fc["why"][:1].upper() + fc["why"][1:] + "."]
    lines += [
        f"**{'Named' if fc['named'] else 'Not named'}** ({fc['why']}). {fc['words']}.",
        "",
        "The curve replaces the named structure's forces other than dry friction and keeps the "
        f"rest: fitted {', '.join(fc['structure'])}; RMS {fc['rms'] * 1e3:.4f} mm on the exact "
        "simulator.",
        "",
    ]
    held = fc.get("held_out")
    if held and held["recordings"]:
        lines += ["| held out | named structure [mm] | with the curve [mm] |", "|---|---:|---:|"]
        lines += [
            f"| {name} | {a * 1e3:.4f} | {b * 1e3:.4f} |"
            for name, a, b in zip(held["recordings"], held["named"], held["curve"], strict=True)
        ]
        lines.append("")
    c = fc["curve"]
    head = " | ".join(f"{q * 1e3:.0f} mm/s" for q in c["speeds"][1:])
    lines += [f"| friction [N] | {head} |", "|---" + "|---:" * (len(c["speeds"]) - 1) + "|"]
    for side, levels in c["levels"].items():
        cells = [
            f"{v:.3f} ± {b:.3f}" if b is not None else f"{v:.3f} (held)"
            for v, b in zip(levels[1:], c["bands"][side][1:], strict=True)
        ]
        lines.append(f"| moving {side} | " + " | ".join(cells) + " |")
    lines += ["", f"Viscous friction beside it: B_eq = {c['b_eq']:.4g} kg/s."]
    if plant_file:
        lines += [f"The cart with the curve: `{plant_file}` (simulate with `--plant`)."]
    if figure:
        lines += ["", f"![friction curve]({figure})"]
    return lines


def named_friction(d, speeds, side: str, b_eq: float) -> np.ndarray:
    """The named structure's friction [N] at ``speeds`` [m/s] moving ``side``, beyond the
    viscous ``b_eq`` q [kg/s] the curve has beside it: Coulomb's level split by its asymmetry,
    viscous friction (B_eq, by direction) above ``b_eq``, Stribeck's fall from the static
    level (the diagnosis's fitted values)."""
    fitted = {n: v["value"] for n, v in d.parameters.items() if v.get("value") is not None}
    have = d.plant.param_names()

    def get(name):
        return float(fitted.get(name, d.plant.get(name) if name in have else 0.0))

    sign = 1.0 if side == "right" else -1.0
    level = get("f_c") + sign * get("f_c_asym")
    q = np.asarray(speeds, dtype=float)
    out = level + (get("B_eq") + sign * get("B_asym") - b_eq) * q
    f_s, v_s = get("f_s"), get("v_stribeck")
    if f_s > level and v_s > 0:
        out = out + (f_s - level) * np.exp(-((q / v_s) ** 2))
    return out


def plot_curve(d, path):
    """The curve's friction beyond its viscous B_eq q against the speed (a log axis: the
    entries are evenly spaced on it), each direction slid, its 90 % band, beside the named
    structure's friction law on the same footing; saved at ``path``."""
    # lazy: matplotlib.pyplot costs 0.3-0.5 s at start-up (python -X importtime), and
    # matplotlib.use("Agg") must not run on import (it sets the process's backend)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = d.friction_curve["curve"]
    speeds = np.asarray(c["speeds"][1:])  # from the anchor: the curve is 0 below it
    fine = np.geomspace(speeds[0] / 2, speeds[-1] * 1.6, 200)
    fig, ax = plt.subplots(figsize=(7.0, 4.4), layout="constrained")
    for k, (side, levels) in enumerate(c["levels"].items()):
        color = f"C{k}"
        level = np.asarray(levels[1:])
        bands = c["bands"][side][1:]
        known = np.array([b is not None for b in bands])
        half = np.array([Z90 * b if b is not None else math.nan for b in bands])
        # Linear in the speed between the entries (curved on the log axis), held beyond.
        ax.plot(fine, np.interp(fine, c["speeds"], levels), "-", color=color, lw=1.6,
                label=f"curve, moving {side}")  # fmt: skip
        inside = fine[(fine >= speeds[known].min()) & (fine <= speeds[known].max())]
        low, high = ((level + s * half)[known] for s in (-1, 1))
        ax.fill_between(inside, np.interp(inside, speeds[known], low),
                        np.interp(inside, speeds[known], high), color=color, alpha=0.25, lw=0,
                        label=f"90 % band, {side}")  # fmt: skip
        if (~known).any():
            ax.plot(speeds[~known], level[~known], "o", mfc="none", color=color,
                    label=f"held (not determined), {side}")  # fmt: skip
        ax.plot(fine, named_friction(d, fine, side, c["b_eq"]), "--", color=color, lw=1,
                label=f"named ({d.chosen}), {side}")  # fmt: skip
    ax.set_xscale("log")
    ax.set_xlabel("speed |y'| [m/s]")
    ax.set_ylabel(f"friction beyond {c['b_eq']:.3g} kg/s × |y'| [N]")
    named = "named" if d.friction_curve["named"] else "not named"
    ax.set_title(f"Friction as a curve of the speed ({named})", fontsize=10)
    ax.legend(fontsize=7, loc="best")
    ax.grid(alpha=0.3, which="both")
    out = plots.save(fig, path, dpi=110)
    plt.close(fig)
    return out
