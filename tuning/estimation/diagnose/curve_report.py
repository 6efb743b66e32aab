"""The friction curves a diagnosis read (:mod:`.friction_curve`) in its report: a section of
Markdown for each, a figure of the friction against the speed (each direction with its 90 %
band) and one of the friction along the track, each beside the friction law of the named
structure it competed with."""

from __future__ import annotations

import math

import numpy as np

from jaxcart import plots

#: The band drawn: +- this many standard errors (90 %, two-sided).
Z90 = 1.645


def curve_section(d, files: dict | None = None) -> list:
    """Markdown lines: for each curve tried (of the speed, of the position), what it shows,
    whether it is named and why, the held-out table and its values; ``files`` {"figure",
    "track_figure", "plant"}: the outputs written (empty when no curve was tried)."""
    fc, files = d.friction_curve, files or {}
    if not fc:
        return []
    lines = ["", "## Friction as a curve of the speed", ""]
    if not fc.get("sides"):
        lines.append(fc["why"][:1].upper() + fc["why"][1:] + ".")
    else:
        lines += _verdict(fc) + _held_table(fc.get("held_out"), "curve") + _speed_table(fc)
        if files.get("figure"):
            lines += ["", f"![friction curve]({files['figure']})"]
    if "track" in fc:
        lines += ["", "## Friction along the track", ""]
        lines += _verdict(fc["track"]) + _held_table(fc.get("held_out"), "track")
        lines += _track_table(fc["track"]["curve"])
        if files.get("track_figure"):
            lines += ["", f"![friction along the track]({files['track_figure']})"]
    if files.get("plant"):
        lines += ["", f"The cart with the curve: `{files['plant']}` (simulate with `--plant`)."]
    return lines


def _verdict(shape: dict) -> list:
    return [
        f"**{'Named' if shape['named'] else 'Not named'}** ({shape['why']}). {shape['words']}.",
        "",
        "The curve replaces the named structure's forces other than dry friction and keeps the "
        f"rest: fitted {', '.join(shape['structure'])}; RMS {shape['rms'] * 1e3:.4f} mm on the "
        "exact simulator.",
        "",
    ]


def _held_table(held, label: str) -> list:
    if not held or not held["recordings"]:
        return []
    lines = ["| held out | named structure [mm] | with the curve [mm] |", "|---|---:|---:|"]
    lines += [
        f"| {name} | {a * 1e3:.4f} | {'-' if b is None else f'{b * 1e3:.4f}'} |"
        for name, a, b in zip(held["recordings"], held["named"], held[label], strict=True)
    ]
    return lines + [""]


def _cells(levels, bands) -> list:
    return [
        f"{v:.3f} ± {b:.3f}" if b is not None else f"{v:.3f} (held)"
        for v, b in zip(levels, bands, strict=True)
    ]


def _speed_table(fc: dict) -> list:
    c = fc["curve"]
    head = " | ".join(f"{q * 1e3:.0f} mm/s" for q in c["speeds"][1:])
    lines = [f"| friction [N] | {head} |", "|---" + "|---:" * (len(c["speeds"]) - 1) + "|"]
    for side, levels in c["levels"].items():
        cells = _cells(levels[1:], c["bands"][side][1:])
        lines.append(f"| moving {side} | " + " | ".join(cells) + " |")
    return lines + ["", f"Viscous friction beside it: B_eq = {c['b_eq']:.4g} kg/s."]


def _track_table(c: dict) -> list:
    head = " | ".join(f"{q:+.2f} m" for q in c["positions"])
    lo, hi = c["span"]
    held = [f"{q:+.2f} m" for q in c["knots"] if q not in c["positions"]]
    return [
        f"| friction [N] at | {head} |",
        "|---" + "|---:" * len(c["positions"]) + "|",
        "| either way | " + " | ".join(_cells(c["levels"], c["bands"])) + " |",
        "",
        f"The recordings cover {lo:+.3f} to {hi:+.3f} m; the levels at the knots they leave "
        f"undetermined ({', '.join(held) or 'none'}) are held at the named f_c. Viscous "
        f"friction beside it: B_eq = {c['b_eq']:.4g} kg/s.",
    ]


def named_friction(d, speeds, side: str, b_eq: float) -> np.ndarray:
    """The named structure's friction [N] at ``speeds`` [m/s] moving ``side``, beyond the
    viscous ``b_eq`` q [kg/s] the curve has beside it: Coulomb's level split by its asymmetry,
    viscous friction (B_eq, by direction) above ``b_eq``, Stribeck's fall from the static
    level (the diagnosis's fitted values)."""
    get = _named_values(d)
    sign = 1.0 if side == "right" else -1.0
    level = get("f_c") + sign * get("f_c_asym")
    q = np.asarray(speeds, dtype=float)
    out = level + (get("B_eq") + sign * get("B_asym") - b_eq) * q
    f_s, v_s = get("f_s"), get("v_stribeck")
    if f_s > level and v_s > 0:
        out = out + (f_s - level) * np.exp(-((q / v_s) ** 2))
    return out


def _named_values(d):
    """name -> the diagnosis's fitted value of it (its cart's where not fitted, 0 where the
    cart lacks it)."""
    fitted = {n: v["value"] for n, v in d.parameters.items() if v.get("value") is not None}
    have = d.plant.param_names()
    return lambda name: float(fitted.get(name, d.plant.get(name) if name in have else 0.0))


def plot_curve(d, path):
    """The curve's friction beyond its viscous B_eq q against the speed (a log axis: the
    entries are evenly spaced on it), each direction slid, its 90 % band, beside the named
    structure's friction law on the same footing; saved at ``path``."""
    # lazy: matplotlib.figure costs 0.3-0.6 s at start-up (python -X importtime); its object
    # API sets no process state (no pyplot figure, no backend switched)
    from matplotlib.figure import Figure

    c = d.friction_curve["curve"]
    speeds = np.asarray(c["speeds"][1:])  # from the anchor: the curve is 0 below it
    fine = np.geomspace(speeds[0] / 2, speeds[-1] * 1.6, 200)
    fig = Figure(figsize=(7.0, 4.4), layout="constrained")
    ax = fig.subplots()
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
    return plots.save(fig, path, dpi=110)


def plot_track(d, path):
    """The friction along the track the curve read (its levels fitted with their 90 % bands,
    those held, the map through them, the stretch the recordings cover shaded), beside the named
    structure's kinetic level (Coulomb's, each direction); saved at ``path``."""
    # lazy: as plot_curve
    from matplotlib.figure import Figure

    from jaxcart.effects.track_friction import TrackFriction

    shape = d.friction_curve["track"]
    c = shape["curve"]
    cart = TrackFriction(f_track=tuple(c["knot_values"]))
    fine = np.linspace(c["knots"][0], c["knots"][-1], 300)
    fig = Figure(figsize=(7.0, 4.4), layout="constrained")
    ax = fig.subplots()
    ax.axvspan(*c["span"], color="0.9", label="covered by the recordings")
    level = np.array([cart.kinetic(float(y), math) for y in fine])
    inside = (fine >= c["positions"][0]) & (fine <= c["positions"][-1])
    ax.plot(fine, np.where(inside, level, np.nan), "-", color="C0", lw=1.6,
            label="curve along the track")  # fmt: skip
    ax.plot(fine, np.where(inside, np.nan, level), ":", color="C0", lw=1,
            label="beyond the levels fitted")  # fmt: skip
    ax.errorbar(c["positions"], c["levels"], yerr=Z90 * np.asarray(c["bands"]), fmt="o",
                color="C0", capsize=3, label="levels fitted, 90 % band")  # fmt: skip
    held = [(q, v) for q, v in zip(c["knots"], c["knot_values"], strict=True)
            if q not in c["positions"]]  # fmt: skip
    if held:
        ax.plot(*zip(*held, strict=True), "o", mfc="none", color="C0",
                label="levels held (not determined)")  # fmt: skip
    get = _named_values(d)
    signs = (1.0, -1.0) if get("f_c_asym") else (0.0,)
    for k, sign in enumerate(signs):  # Coulomb's level, split by its asymmetry where it has one
        side = {1.0: ", right", -1.0: ", left", 0.0: ""}[sign]
        ax.axhline(get("f_c") + sign * get("f_c_asym"), ls="--", lw=1, color=f"C{k + 1}",
                   label=f"named ({d.chosen}){side}")  # fmt: skip
    ax.set_xlabel("position along the track y [m]")
    ax.set_ylabel("kinetic friction [N]")
    named = "named" if shape["named"] else "not named"
    ax.set_title(f"Friction along the track ({named})", fontsize=10)
    ax.legend(fontsize=7, loc="best")
    ax.grid(alpha=0.3)
    return plots.save(fig, path, dpi=110)
