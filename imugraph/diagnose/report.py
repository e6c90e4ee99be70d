"""The diagnosis report: diagnosis.json (DESIGN.md contract), diagnosis.md and its figures, all atomic.

Figures: gap_over_time.png (the gap-vs-time curve per channel with its flag threshold, the simulation's
own curve and the located windows) and residuals.png (whitened residuals of the effect's channel before
and after the winning effect, with the simulated residuals for reference).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from imugraph.diagnose.gap import CHANNELS
from imugraph.io.figures import save_figure_atomic
from imugraph.io.writers import atomic_write_text, json_ready

_COLORS = ("tab:red", "tab:green", "tab:blue")
_MAX_POINTS = 6000


def plot_gap_over_time(diag, path) -> Path:
    """Gap-vs-time per channel (real vs simulation, simulation vs simulation, threshold, locations)."""
    fig = Figure(figsize=(10, 7))
    axes = fig.subplots(3, 1, sharex=True)
    curve = diag.curve
    for ax, c in zip(axes, CHANNELS):
        ax.plot(curve.t, curve.values[c], color="k", lw=1, label="real vs simulation")
        ax.plot(curve.t, diag.null_curve[c], color="0.6", lw=1, label="simulation vs simulation")
        ax.axhline(curve.threshold[c], color="tab:orange", ls="--", lw=1, label="flag threshold")
        for loc in diag.locations:
            if loc["channel"] == c:
                ax.axvspan(loc["t_start"], loc["t_end"], color="tab:red", alpha=0.15)
        ax.set_ylabel(f"gap {c}")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(f"{diag.real.session.name}: sim-to-real gap per {curve.t[1] - curve.t[0]:.0f} s step "
                      f"(verdict: {diag.verdict})")
    axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    return save_figure_atomic(fig, path)


def plot_residuals(diag, path, channel: str | None = None) -> Path:
    """Whitened residuals of one channel (the winner's, else the channel with the largest gap/null ratio)
    over time: real before, real after the winning effect (if any), and the simulation."""
    from imugraph.diagnose.run import best_result

    best = best_result(diag)
    if channel is None:
        channel = best.channel if best else max(CHANNELS, key=lambda c: diag.gap_raw[c] / max(diag.null_gap[c], 1e-12))
    s = diag.real.session
    step = max(1, s.n // _MAX_POINTS)
    t = s.t[::step]
    sigma = diag.real.sigma[channel]
    rows = [("real, base model", diag.real.residuals[channel])]
    if diag.residuals_after is not None:
        rows.append((f"real, with {diag.verdict}", diag.residuals_after[channel]))
    rows.append(("simulation from the fit", diag.sim.residuals[channel]))
    fig = Figure(figsize=(10, 2.6 * len(rows)))
    axes = fig.subplots(len(rows), 1, sharex=True, sharey=True)
    for ax, (label, r) in zip(np.atleast_1d(axes), rows):
        z = (r / sigma)[::step]
        for a in range(3):
            ax.plot(t, z[:, a], color=_COLORS[a], lw=0.5, label="xyz"[a])
        ax.set_ylabel("whitened")
        ax.set_title(f"{channel} residual: {label}", fontsize=9)
        ax.grid(alpha=0.3)
        if best is not None and best.t_start is not None:
            ax.axvspan(best.t_start, best.t_end, color="tab:orange", alpha=0.12)
    np.atleast_1d(axes)[0].legend(loc="upper right", fontsize=8, ncol=3)
    np.atleast_1d(axes)[-1].set_xlabel("t (s)")
    fig.tight_layout()
    return save_figure_atomic(fig, path)


def _cell(text) -> str:
    """A markdown table cell: '|' escaped (a size unit "fraction of |m|" or an error text split the row into
    more cells than the header), newlines folded."""
    return " ".join(str(text).split()).replace("|", "\\|")


def markdown(diag, figures: dict) -> str:
    """diagnosis.md text (every table row has as many cells as its header: free text goes through `_cell`)."""
    s = diag.real.session
    lines = [f"# Diagnosis of {s.name}", "",
             f"{s.n} samples, {s.t[-1] - s.t[0]:.1f} s at {s.rate:.1f} Hz ({s.source}).", "",
             f"**Verdict: `{diag.verdict}`**", "",
             f"Base model: the magnetometer's lag behind the gyro, "
             f"{1e3 * float(diag.real.info.get('mag_delay_s', 0.0)):.1f} ms, is part of it (removed before the fit).", "",
             "## Gap per channel (real vs simulation from the fitted model)", "",
             "| channel | gap (excess over floor) | real vs sim | noise floor (sim vs sim) | ratio |",
             "|---|---|---|---|---|"]
    for c in CHANNELS:
        lines.append(f"| {c} | {diag.gap[c]:.3f} | {diag.gap_raw[c]:.3f} | {diag.null_gap[c]:.3f} | "
                     f"{diag.gap_raw[c] / max(diag.null_gap[c], 1e-12):.1f} |")
    lines += ["", "## Where", ""]
    if diag.locations:
        lines += ["| channel | t_start (s) | t_end (s) | score |", "|---|---|---|---|"]
        lines += [f"| {d['channel']} | {d['t_start']:.1f} | {d['t_end']:.1f} | {d['score']:.2f} |"
                  for d in diag.locations[:20]]
    else:
        lines.append("No window stands out from the rest of the recording.")
    lines += ["", f"![gap over time]({figures['gap']})", "",
              "## Which effect (cross-validated on held-out time blocks)", "",
              "| rank | effect | channel | window (s) | gap before | gap after | shrink | penalised | "
              "log score (nats) | params | size / threshold | significant | relevant | fit |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(diag.effects, 1):
        win = "—" if r.t_start is None else f"{r.t_start:.1f}–{r.t_end:.1f}"
        if r.error:
            lines.append(f"| {i} | {r.name} | {r.channel} | — | — | — | — | — | failed: {_cell(r.error)} | | | | | |")
            continue
        sz = r.size or {}
        lines.append(f"| {i} | {r.name} | {r.channel} | {win} | {r.gap_before:.3f} | {r.gap_after:.3f} | "
                     f"{r.shrink:.2f} | {r.penalised:.2f} | {r.loglik_gain:+.4f} | {r.n_params} | "
                     f"{sz.get('value', float('nan')):.3g} / {sz.get('threshold', float('nan')):.3g} "
                     f"{_cell(sz.get('unit', ''))} | {'yes' if r.significant else 'no'} | "
                     f"{'yes' if r.relevant else 'no'} | {r.stage} |")
    lines += ["", f"![residuals]({figures['residuals']})", "",
              "Gap: 1-Wasserstein distance between real and simulated whitened residuals plus the mean "
              "absolute difference of their autocorrelations (docs/diagnose.md). Shrink = 1 − gap after / "
              "gap before on held-out time; penalised shrink also charges the parameters the effect adds "
              "and any channel it makes worse. Log score: the held-out log predictive density gain of the "
              "extended model over the base model per sample, summed over the channels, net of a BIC cost "
              "(a proper scoring rule, (A4')). The verdict is the best-ranked effect that is significant "
              "(gap ≥ 2 × noise floor and penalised shrink ≥ margin, or, for an effect scored on its "
              "support, log score > 0) AND relevant (fitted size ≥ its physical "
              "threshold); fit = screen (first-order, trajectory fixed) or refit (base model refitted).", ""]
    return "\n".join(lines)


def write_report(diag, out_dir) -> dict:
    """Write diagnosis.json, diagnosis.md, gap_over_time.png and residuals.png into out_dir.

    Returns: name → path of the files written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = {"gap": "gap_over_time.png", "residuals": "residuals.png"}
    paths = {"gap_over_time.png": plot_gap_over_time(diag, out / figs["gap"]),
             "residuals.png": plot_residuals(diag, out / figs["residuals"])}
    paths["diagnosis.json"] = atomic_write_text(out / "diagnosis.json",
                                                json.dumps(json_ready(diag.to_json()), indent=1))
    paths["diagnosis.md"] = atomic_write_text(out / "diagnosis.md", markdown(diag, figs))
    return paths


def summary_table(diag) -> str:
    """A short stdout table: verdict, gap per channel, top effects."""
    lines = [f"diagnosis of {diag.real.session.name}: verdict {diag.verdict} (base model's magnetometer lag "
             f"{1e3 * float(diag.real.info.get('mag_delay_s', 0.0)):.1f} ms)",
             "  gap " + "  ".join(f"{c} {diag.gap[c]:.3f} (floor {diag.null_gap[c]:.3f})" for c in CHANNELS)]
    for loc in diag.locations[:3]:
        lines.append(f"  location {loc['channel']} {loc['t_start']:.1f}–{loc['t_end']:.1f} s "
                     f"score {loc['score']:.2f}")
    for r in diag.effects[:5]:
        if r.error:
            lines.append(f"  {r.name:22s} failed: {r.error}")
        else:
            sz = r.size or {}
            lines.append(f"  {r.name:22s} {r.channel}  shrink {r.shrink:+.2f}  penalised {r.penalised:+.2f}"
                         f"  log score {r.loglik_gain:+.3f}"
                         f"  size {sz.get('value', float('nan')):.3g}/{sz.get('threshold', float('nan')):.3g}"
                         f"{'' if r.relevant else ' (below relevance)'}"
                         + ("" if r.t_start is None else f"  window {r.t_start:.1f}–{r.t_end:.1f} s"))
    return "\n".join(lines)
