"""The tuning run's plot: the training cost and its terms, and the validation curve."""

from __future__ import annotations

from jaxsync.io import results as _results


def plot_loss(history: list[dict], path: str, validation: list[dict] | None = None, selected=None) -> None:
    """The training cost and its terms; with validation, a second panel of the
    validation settled peak and grip error, the selected iterate marked."""
    plt = _results.pyplot()

    it = [r["iteration"] for r in history]
    panels = 2 if validation else 1
    fig, axes = plt.subplots(panels, 1, figsize=(7, 4 * panels), squeeze=False)
    ax = axes[0, 0]
    ax.semilogy(it, [r["cost"] for r in history], label="batch cost", color="k")
    for k in sorted(k for k in history[0] if k.startswith("term_")):
        ax.semilogy(it, [max(r[k], 1e-12) for r in history], lw=0.8, label=k[5:])
    ax.set_xlabel("iteration")
    ax.set_ylabel("cost (training batch)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if validation:
        ax = axes[1, 0]
        vi = [v["iteration"] for v in validation]
        peak = [v["settled_peak_resultant_N"] or float("nan") for v in validation]
        grip = [100 * (v["grip_force_error_rel"] or float("nan")) for v in validation]
        ax.plot(vi, peak, "o-", color="C0", label="settled peak resultant (N)")
        ax.set_xlabel("iteration")
        ax.set_ylabel("validation settled peak resultant (N)", color="C0")
        ax.grid(alpha=0.3)
        ax2 = ax.twinx()
        ax2.plot(vi, grip, "s--", color="C3", label="grip error (%)")
        ax2.axhline(grip[0], color="C3", lw=0.6, ls=":")
        ax2.set_ylabel("validation grip-force error (%)", color="C3")
        if selected is not None:
            ax.axvline(selected["iteration"], color="k", lw=0.8, ls="--")
            ax.set_title(f"selected iterate: {selected['iteration']}", fontsize=9)
    fig.tight_layout()
    _results.save_figure(fig, path)
    plt.close(fig)
