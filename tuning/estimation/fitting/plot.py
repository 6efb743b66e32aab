"""A fit's overlay plot: each recording and the model before and after, with residuals."""

from __future__ import annotations

from pathlib import Path

from hw.atomicio import save_figure
from tuning.estimation.fitting.names import fittable, unit_of
from tuning.estimation.fitting.result import FitResult


def plot_fit(result: FitResult, path, *, dpi: int = 130) -> Path:
    """Overlay of each recording and the model before and after the fit (exact simulator solid,
    smooth simulator dashed), with the residuals below; saves a PNG at ``path``."""
    # lazy: matplotlib.figure costs 0.3-0.5 s at start-up (python -X importtime) after
    # tuning.estimation.fit; the command preloads it in a thread (jaxcart.plots.preload)
    from matplotlib.figure import Figure

    segs = result.segments
    fig = Figure(figsize=(8.0 * min(len(segs), 2) ** 0.5 + 1, 5.5), layout="constrained")
    axes = fig.subplots(2, len(segs), squeeze=False, sharex="col", height_ratios=(3, 2))
    for k, seg in enumerate(segs):
        ax, ax_r = axes[0, k], axes[1, k]
        t = seg.time
        ax.plot(t, seg.measured, color="black", lw=2.2, alpha=0.35, label="recorded")
        if seg.before_exact is not None:
            ax.plot(t, seg.before_exact, color="0.55", ls=":", lw=1.2, label="model before (exact)")
        else:
            ax.plot(t, seg.before, color="0.55", ls=":", lw=1.2, label="model before (smooth)")
        if seg.after_exact is not None:
            ax.plot(t, seg.after_exact, color="tab:blue", lw=1.2, label="fitted model (exact)")
        ax.plot(t, seg.after, color="tab:orange", ls="--", lw=1.2, label="fitted model (smooth)")
        ax.set_ylabel("position y [m]")
        ax.set_title(f"{seg.name} ({seg.kind}, {t[0]:.3f} to {t[-1]:.3f} s)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        if seg.after_exact is not None:
            ax_r.plot(
                t,
                (seg.after_exact - seg.measured) * 1e3,
                color="tab:blue",
                lw=1.0,
                label=f"exact, RMS {seg.rms_after_exact * 1e3:.3g} mm",
            )
        ax_r.plot(
            t,
            (seg.after - seg.measured) * 1e3,
            color="tab:orange",
            ls="--",
            lw=1.0,
            label=f"smooth, RMS {seg.rms_after * 1e3:.3g} mm",
        )
        ax_r.axhline(0.0, color="0.5", lw=0.6)
        ax_r.set_xlabel("time t [s]")
        ax_r.set_ylabel("model - recorded [mm]")
        ax_r.grid(alpha=0.3)
        ax_r.legend(fontsize=8, loc="best")
    fitted = ", ".join(
        f"{n} = {e.value:.4g} ± {e.stderr:.2g} {unit_of(n)}".rstrip()
        if e.identifiable
        else f"{n}: not identifiable"
        for n, e in result.params.items()
    )
    if not fitted:  # a prediction (cross_predict): show the values it ran with
        held = ", ".join(f"{n} = {v:.4g}" for n, v in result.values.items() if n in fittable())
        fitted = f"prediction with {held or 'the nominal plant'}"
    fig.suptitle(f"jaxcart fit: {fitted}", fontsize=11)

    return save_figure(fig, path, dpi=dpi)
