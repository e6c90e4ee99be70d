"""The body diagnosis report: diagnosis.json (DESIGN.md keys + body extras), diagnosis.md, gap_over_time.png
(gap-vs-time of the sensor × channel that holds the verdict, else the largest located one) and residuals.png
(that sensor's whitened residuals before/after the winning effect, with simulation A's), all atomic.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from imugraph.diagnose.body.fit import CHANNELS
from imugraph.io.figures import save_figure_atomic
from imugraph.io.writers import atomic_write_text, json_ready

_MAX_POINTS = 6000


def focus(diag) -> tuple[str, str]:
    """(sensor, channel) the figures show: the verdict's, else the best location's, else the largest gap."""
    if diag.verdict != "none":
        best = next(e for e in diag.effects if e["name"] == diag.verdict and e["sensor"] == diag.sensor)
        return diag.sensor, best["channel"]
    if diag.locations:
        return diag.locations[0]["sensor"], diag.locations[0]["channel"]
    return max(((n, c) for n, g in diag.gaps.items() for c in g), key=lambda nc: diag.gaps[nc[0]][nc[1]]["gap"])


def plot_gap_over_time(diag, path) -> Path:
    """Gap-vs-time per channel of the focus sensor (real vs A, B vs A, threshold, locations)."""
    sensor, _ = focus(diag)
    chans = [c for c in CHANNELS if c in diag.curves.get(sensor, {})]
    fig = Figure(figsize=(10, 1.8 * max(len(chans), 1) + 1))
    axes = np.atleast_1d(fig.subplots(max(len(chans), 1), 1, sharex=True))
    for ax, c in zip(axes, chans):
        cv = diag.curves[sensor][c]
        ax.plot(cv["t"], cv["real"], color="k", lw=1, label="real vs simulation")
        ax.plot(cv["t"], cv["null"], color="0.6", lw=1, label="simulation vs simulation")
        ax.axhline(cv["threshold"], color="tab:orange", ls="--", lw=1, label="flag threshold")
        for loc in diag.locations:
            if loc["sensor"] == sensor and loc["channel"] == c:
                ax.axvspan(loc["t_start"], loc["t_end"], color="tab:red", alpha=0.15)
        ax.set_ylabel(f"gap {c}")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(f"{sensor}: sim-to-real gap (verdict: {diag.verdict})")
    axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    return save_figure_atomic(fig, path)


def plot_residuals(diag, path) -> Path:
    """Whitened residuals of the focus sensor × channel: real (base), real with the verdict's effect, sim A."""
    from imugraph.diagnose.body.gap import model_sigma

    sensor, channel = focus(diag)
    real, a = diag.fits["real"].sensors[sensor], diag.fits["A"].sensors[sensor]
    sigma = model_sigma(diag.fits["A"])[sensor][channel]
    t = real.time_base(channel)
    rows = [("real, base model", real.residuals[channel])]
    if diag.verdict != "none":
        rows.append((f"real, with {diag.verdict}", diag.corrections[(diag.verdict, sensor)].residuals[channel]))
    rows.append(("simulation of the fitted model", a.residuals[channel]))
    step = max(1, t.size // _MAX_POINTS)
    fig = Figure(figsize=(10, 2.2 * len(rows) + 1))
    axes = np.atleast_1d(fig.subplots(len(rows), 1, sharex=True, sharey=True))
    for ax, (label, r) in zip(axes, rows):
        z = r[::step] / sigma
        ax.plot(t[::step], z[:, : min(3, z.shape[1])], lw=0.6)
        ax.set_ylabel("whitened")
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t (s)")
    fig.suptitle(f"{sensor} {channel} residuals")
    fig.tight_layout()
    return save_figure_atomic(fig, path)


def markdown(diag) -> str:
    """diagnosis.md: verdict, gap table per sensor × channel, locations, ranked effects, timing."""
    lines = [f"# Body diagnosis: verdict **{diag.verdict}**" + (f" on **{diag.sensor}**" if diag.sensor else ""), "",
             "Method: docs/diagnose_body.md. Gap = max(0, G1(real, sim A) − G1(sim B, sim A)) per sensor × channel "
             "(gyr, acc, pos, joint: keyframe-interval residuals; jacc: per-sample joint-acceleration residual).", "",
             "| sensor | " + " | ".join(CHANNELS) + " |", "|---|" + "---|" * len(CHANNELS)]
    for n, g in diag.gaps.items():
        lines.append(f"| {n} | " + " | ".join(f"{g[c]['gap']:.3f} ({g[c]['null_gap']:.3f})" for c in CHANNELS) + " |")
    lines += ["", "(in brackets: the noise floor, simulation B vs A)", "", "## Locations", ""]
    lines += [f"- {loc['sensor']} {loc['channel']}: {loc['t_start']:.1f}–{loc['t_end']:.1f} s (score {loc['score']:.2f})"
              for loc in diag.locations[:20]] or ["none"]
    lines += ["", "## Effects (held-out, ranked by log-score gain G)", "",
              "| effect | sensor | channel | G (nats/sample) | shrink | size | significant | relevant |",
              "|---|---|---|---|---|---|---|---|"]
    for e in diag.effects[:20]:
        lines.append(f"| {e['name']} | {e['sensor']} | {e['channel']} | {e['loglik_gain']:+.3f} | {e['shrink']:.2f} | "
                     f"{e['size'].get('value', 0):.4g} {e['size'].get('unit', '')} | {e['significant']} | {e['relevant']} |")
    lines += ["", "![gap over time](gap_over_time.png)", "", "![residuals](residuals.png)", "",
              "Timing (s): " + ", ".join(f"{k} {v:.1f}" for k, v in diag.timing.items())]
    return "\n".join(lines) + "\n"


def write_report(diag, out: Path) -> dict:
    """Write diagnosis.json, diagnosis.md and the two figures into `out`; {name: path}."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"diagnosis.json": atomic_write_text(out / "diagnosis.json",
                                                 json.dumps(json_ready(diag.to_json()), indent=1)),
             "diagnosis.md": atomic_write_text(out / "diagnosis.md", markdown(diag)),
             "gap_over_time.png": plot_gap_over_time(diag, out / "gap_over_time.png"),
             "residuals.png": plot_residuals(diag, out / "residuals.png")}
    return paths


def summary_table(diag) -> str:
    """A few printed lines: verdict, the three best effects, the largest gaps."""
    lines = [f"verdict: {diag.verdict}" + (f" (sensor {diag.sensor})" if diag.sensor else "")]
    for e in diag.effects[:3]:
        lines.append(f"  {e['name']:<20} {e['sensor']:<14} G {e['loglik_gain']:+.3f}  shrink {e['shrink']:.2f}  "
                     f"significant {e['significant']}  relevant {e['relevant']}")
    top = sorted(((g[c]["gap"], n, c) for n, g in diag.gaps.items() for c in g), reverse=True)[:3]
    lines += [f"  gap {n} {c}: {v:.3f}" for v, n, c in top]
    return "\n".join(lines)
