"""Figures of an incremental run (`imugraph stream`): the calibration as it evolved, the filtered and smoothed
orientation over time, and the time each solver update took.

Each function writes one PNG atomically (`figures.save_figure_atomic`) and returns the Figure. Inputs are what
`stream_session` returns (`StreamResult`) and what `imugraph stream` writes (calibration_history.json rows):

- calibration: one row per `calib_every_s` {t (s since the first sample), D, o, dip_deg, std {D, o, dip_deg}};
  with θ as a graph state the streamed θ̂ and its marginal std from iSAM2 (stream_online.calibration_history).
  Plotted: the hard iron o, the diagonal of D (the magnetometer's per-axis gain) and the dip δ, each with its
  ±1 std band, against the end calibration (and an optional reference, e.g. a batch calibration);
- orientation: the total angle of eq. (1) of `imugraph.evaluate` (best time shift and constant heading offset)
  of the filtered estimate (available when each sample arrived) and of the smoothed one (at the end) against a
  reference orientation; without a reference, the angle between the filtered and the smoothed estimate;
- timing: the wall (and thread CPU) time of each keyframe update against the stream time, with p50 / p99.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from matplotlib.figure import Figure

from imugraph.errors import SessionError
from imugraph.io.figures import save_figure_atomic

_AXES = ("x", "y", "z")
_COLORS = ("tab:red", "tab:green", "tab:blue")


def _history_arrays(history: Sequence[dict], path: Path) -> dict:
    """{t (R,), o (R, 3), o_std, Ddiag (R, 3), Ddiag_std, dip (R,), dip_std} from calibration_history rows
    (std NaN where a row has none)."""
    try:
        t = np.array([float(r["t"]) for r in history])
        o = np.array([np.asarray(r["o"], float).reshape(3) for r in history])
        Dd = np.array([np.diag(np.asarray(r["D"], float).reshape(3, 3)) for r in history])
        dip = np.array([float(r["dip_deg"]) for r in history])
    except (KeyError, TypeError, ValueError) as exc:
        raise SessionError(str(path), "calibration_history", f"a row without t, D (3×3), o (3,), dip_deg ({exc})",
                           "rows as imugraph stream writes them") from None

    def std(name: str, shape: tuple) -> np.ndarray:
        out = np.full((len(history),) + shape, np.nan)
        for i, r in enumerate(history):
            s = (r.get("std") or {}).get(name)
            if s is not None:
                s = np.asarray(s, float)
                out[i] = np.diag(s.reshape(3, 3)) if name == "D" else s.reshape(shape)
        return out

    return {"t": t, "o": o, "o_std": std("o", (3,)), "Ddiag": Dd, "Ddiag_std": std("D", (3,)), "dip": dip,
            "dip_std": std("dip_deg", ())}


def plot_stream_calibration(path: str | os.PathLike, history: Sequence[dict], end, reference=None, *,
                            title: str = "Calibration as it was streamed",
                            reference_label: str = "reference") -> Figure:
    """3 rows: hard iron o (x, y, z), D's diagonal, dip δ against the stream time, each ±1 std (shaded); the end
    calibration `end` (a Calibration: dashed) and an optional `reference` Calibration (dotted, e.g. the batch's).

    Raises:
        SessionError: no history row, or a row without t, D, o, dip_deg.
    """
    path = Path(path)
    if not history:
        raise SessionError(str(path), "calibration_history", "no row", "≥ 1 row (online calibration on)")
    h = _history_arrays(history, path)
    fig = Figure(figsize=(12, 9), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    panels = (("o", "o_std", "hard iron o", lambda c: np.asarray(c.o, float)),
              ("Ddiag", "Ddiag_std", "D diagonal", lambda c: np.diag(np.asarray(c.D, float))))
    for ax, (key, skey, label, of) in zip(axes[:2], panels):
        for i in range(3):
            y, s = h[key][:, i], h[skey][:, i]
            ax.plot(h["t"], y, color=_COLORS[i], lw=1.2, label=f"{label} {_AXES[i]}")
            ax.fill_between(h["t"], y - s, y + s, color=_COLORS[i], alpha=0.15, lw=0)
            ax.axhline(of(end)[i], color=_COLORS[i], ls="--", lw=0.9)
            if reference is not None:
                ax.axhline(of(reference)[i], color=_COLORS[i], ls=":", lw=1.2)
        ax.set_ylabel(f"{label} [mag. unit]")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8, ncol=3)
    ax = axes[2]
    ax.plot(h["t"], h["dip"], color="k", lw=1.2, label="dip δ")
    ax.fill_between(h["t"], h["dip"] - h["dip_std"], h["dip"] + h["dip_std"], color="k", alpha=0.15, lw=0)
    ax.axhline(float(end.dip_deg), color="k", ls="--", lw=0.9, label="end")
    if reference is not None:
        ax.axhline(float(reference.dip_deg), color="k", ls=":", lw=1.2, label=reference_label)
    ax.set_ylabel("dip [deg]")
    ax.set_xlabel("stream time [s]")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{title} (shaded ±1 std; dashed: end"
                 + (f"; dotted: {reference_label})" if reference is not None else ")"))
    save_figure_atomic(fig, path)
    return fig


def plot_stream_orientation(path: str | os.PathLike, t: np.ndarray, filtered: np.ndarray, smoothed: np.ndarray,
                            reference: Optional[np.ndarray] = None, mask: Optional[np.ndarray] = None, *,
                            title: str = "Orientation", reference_label: str = "reference") -> Figure:
    """Error angle over time of the filtered and the smoothed orientation against `reference` (eq. (1) of
    imugraph.evaluate at its best shift and heading offset, over `mask`), or without a reference the angle between
    the filtered and the smoothed estimate. The RMS of each is in the legend.

    reference_label: what the reference is, in the legend ("filtered vs <label>"): pass
    `imugraph.commands.common.reference_label(session)` — "truth", or "reference [<meta quat_source>]" when the
    session's quat is a device's own estimate (an onboard AHRS is no truth), as the console score and heading.png say.

    Raises:
        SessionError: arrays whose shapes do not match t.
    """
    from imugraph.evaluate import orientation_error_series
    from imugraph.geometry import quat_angle

    path = Path(path)
    t = np.asarray(t, float)
    for name, q in (("filtered", filtered), ("smoothed", smoothed)) + ((("reference", reference),)
                                                                       if reference is not None else ()):
        if np.shape(q) != (t.shape[0], 4):
            raise SessionError(str(path), name, f"shape {np.shape(q)}", f"({t.shape[0]}, 4) like t")
    fig = Figure(figsize=(12, 4), layout="constrained")
    ax = fig.subplots()
    if reference is not None:
        for name, q, c in (("filtered", filtered, "tab:orange"), ("smoothed", smoothed, "tab:blue")):
            idx, err = orientation_error_series(np.asarray(q, float), np.asarray(reference, float), mask)
            ax.plot(t[idx], err, color=c, lw=0.8,
                    label=f"{name} vs {reference_label}, RMS {np.sqrt(np.mean(err ** 2)):.2f}°")
        ax.set_ylabel("error angle [deg]")
    else:
        d = np.rad2deg(quat_angle(np.asarray(filtered, float), np.asarray(smoothed, float)))
        ok = np.isfinite(d)
        ax.plot(t[ok], d[ok], color="tab:orange", lw=0.8,
                label=f"filtered vs smoothed, RMS {np.sqrt(np.mean(d[ok] ** 2)):.2f}°")
        ax.set_ylabel("angle [deg]")
    ax.set_xlabel("time [s]")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title)
    save_figure_atomic(fig, path)
    return fig


def plot_stream_timing(path: str | os.PathLike, t_update: np.ndarray, update_ms: np.ndarray,
                       update_cpu_ms: Optional[np.ndarray] = None, *, title: str = "Time per update") -> Figure:
    """Each keyframe update's wall time (and thread CPU time) against the stream time, with p50 / p99 lines; a
    log-scaled histogram beside it.

    Raises:
        SessionError: t_update and update_ms of different lengths, or no update.
    """
    path = Path(path)
    t_update, ms = np.asarray(t_update, float), np.asarray(update_ms, float)
    if ms.size == 0 or t_update.shape != ms.shape:
        raise SessionError(str(path), "update_ms", f"{ms.size} updates for {t_update.size} times",
                           "one time per update, ≥ 1 update")
    fig = Figure(figsize=(12, 4), layout="constrained")
    ax, axh = fig.subplots(1, 2, width_ratios=(3, 1))
    series = [("wall", ms, "tab:gray")]
    if update_cpu_ms is not None and np.size(update_cpu_ms) == ms.size:
        series.append(("thread CPU", np.asarray(update_cpu_ms, float), "tab:blue"))
    bins = np.logspace(np.log10(max(min(x[x > 0].min() for _, x, _ in series), 1e-3)),
                       np.log10(max(x.max() for _, x, _ in series)), 40)
    for name, x, c in series:
        p50, p99 = np.percentile(x, [50, 99])
        ax.scatter(t_update, x, s=2, color=c, alpha=0.5, label=f"{name}: p50 {p50:.2f} ms, p99 {p99:.2f} ms")
        ax.axhline(p99, color=c, ls="--", lw=0.9)
        axh.hist(x[x > 0], bins=bins, color=c, alpha=0.5, orientation="horizontal")
    for a in (ax, axh):
        a.set_yscale("log")
        a.grid(alpha=0.3)
    ax.set_xlabel("stream time [s]")
    ax.set_ylabel("update time [ms] (dashed: p99)")
    axh.set_xlabel("updates")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title)
    save_figure_atomic(fig, path)
    return fig
