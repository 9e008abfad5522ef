"""A tuning run's report: its plot (the training cost and its terms, and the
validation curve) and the lines that say what it gave."""

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


def summary_lines(summary, out: str) -> list[str]:
    """What a tuning job gave (a ``pipeline.TuneSummary``), in lines: the
    held-out figures before and after, the warning when the kept gains score
    worse than the start, the MuJoCo C check, and the files written in ``out``."""
    b, a = summary.peak_before, summary.peak_after
    lines = [
        f"held-out settled peak resultant: {_num(b, '.5f')} N -> {_num(a, '.5f')} N" + change_text(b, a),
        f"held-out grip-force error: {_num(summary.grip_error_before, '.4f')} -> "
        f"{_num(summary.grip_error_after, '.4f')}",
    ]
    c = getattr(summary, "convergence", None)
    if c is not None:
        lines.append(convergence_text(c))
    if summary.kept_worse_than_start:
        lines.append(worse_text(summary))
    if summary.mujoco_check is not None:
        lines.append(mujoco_text(summary.mujoco_check))
    d = getattr(summary, "deployment", None)
    if d is not None and not d["exports"]:
        more = f" (and {len(d['problems']) - 1} more)" if len(d["problems"]) > 1 else ""
        lines.append(
            f"WARNING: jaxsync export --format ros2-admittance refuses these gains at {d['update_rate_hz']} Hz: "
            f"{d['problems'][0]}{more}; tune through the rule (--controller ros2_admittance) for gains it runs"
        )
    kept = [s for s in getattr(summary, "starts", ()) if s["kept"]]
    if kept:
        lines.append(f"kept the start on seed {kept[0]['seed']} of {len(summary.starts)} (the lowest validation "
                     f"settled peak; every start in {out}/seed_*)")  # fmt: skip
    lines.append(f"results in {out}: gains.json (selected), gains_last.json, history.csv, loss.png, summary.json")
    return lines


def convergence_text(c: dict) -> str:
    """Whether the run converged (``tune_state.convergence_record``), why, and what it cost."""
    cost = (
        f"{c['iterations']} iterations, {c['gradient_calls']} gradients, {c['value_calls']} forward-only costs, "
        f"{c['training_rollouts']} training and {c['validation_rollouts']} validation rollouts, "
        f"{c['seconds']:.0f} s"
    )
    if c["converged"]:
        return f"converged ({c['why']}) after {cost}"
    return (
        f"WARNING: not converged ({c['why']}) after {cost}; a longer run may still lower it (--resume with more "
        "--iterations)"
    )


def worse_text(summary) -> str:
    """The warning that the kept gains score worse than the start (``kept_worse_than_start``)."""
    if summary.validation:
        kept = f"iteration {summary.selected_iteration}, selected by validation"
    else:
        kept = "the last iterate: validate_every 0 selects none"
    return (
        f"WARNING: the kept gains ({kept}) score worse than the starting gains on the held-out scenarios: "
        + "; ".join(summary.kept_worse_than_start)
        + ". gains.json holds them; the starting gains may be the better choice"
        + ("" if summary.validation else " (validating every N iterations keeps the best validated iterate)")
    )


def mujoco_text(c: dict) -> str:
    """The MuJoCo C check's line (jaxsync.sim.crosscheck.sim_to_sim's result): both
    improvement factors, flagged when they disagree or an object was dropped."""
    head = (
        f"on {c['scenarios']} held-out scenarios, settled peak before -> after: MJX {_num(c['mjx_before_N'], '.5f')} "
        f"-> {_num(c['mjx_after_N'], '.5f')} N ({_num(c['factor_mjx'], '.2f')}x), MuJoCo C "
        f"{_num(c['mujoco_before_N'], '.5f')} -> {_num(c['mujoco_after_N'], '.5f')} N "
        f"({_num(c['factor_mujoco'], '.2f')}x): "
    )
    if c["agree"]:
        return head + f"agree within {100 * c['tolerance']:.0f} %"
    why = "; ".join(c.get("problems") or [f"they differ by more than {100 * c['tolerance']:.0f} %"])
    return head + f"WARNING: MuJoCo C and MJX disagree: {why} (docs/export.md)"


def _num(v: float | None, fmt: str) -> str:
    """``v`` formatted, or 'n/a' (every scenario dropped)."""
    return "n/a" if v is None else format(v, fmt)


def change_text(before: float | None, after: float | None) -> str:
    """' (2.73x lower)', ' (8.66x higher)' or ' (unchanged)': the factor always
    above 1 as printed, the direction in words."""
    if not before or not after:
        return ""
    if f"{before / after:.2f}" == "1.00":
        return " (unchanged)"
    if after <= before:
        return f" ({before / after:.2f}x lower)"
    return f" ({after / before:.2f}x higher)"
