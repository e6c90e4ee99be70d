"""Figures written as PNG next to the numbers they show (matplotlib, Agg canvas, no pyplot state).

Every function returns the `Figure` and writes the PNG atomically: it renders to a temporary file in
the destination directory, then `os.replace`s it onto the target, so a reader never sees half a file
and no temporary file survives an error.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from imugraph.errors import SessionError
from imugraph.geometry import quat_to_rotmat, quat_to_rotvec, rotmat_to_quat

_AXES = ("x", "y", "z")
_COLORS = ("tab:red", "tab:green", "tab:blue")
_UNITS = {"gyr": "rad/s", "acc": "m/s²", "mag": "unit field"}
_MAX_SCATTER = 4000


def save_figure_atomic(fig: Figure, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Render `fig` as PNG to `path` through a temporary file in the same directory + os.replace.

    Args:
        fig: the figure.
        path: destination (.png); missing parent directories are created.
        dpi: resolution, dots per inch.

    Returns:
        The destination path.
    """
    from imugraph.io.writers import atomic_write_bytes

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return atomic_write_bytes(Path(path), buf.getvalue())


def _as_n3(name: str, value: np.ndarray, path: Path, n: Optional[int] = None) -> np.ndarray:
    arr = np.asarray(value, float)
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and arr.shape[0] != n):
        want = f"({n if n is not None else 'N'}, 3)"
        raise SessionError(str(path), name, f"shape {arr.shape}", want)
    return arr


def _subsample(n: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(n, _MAX_SCATTER)).astype(int)) if n else np.arange(0)


def plot_calibration(
    path: str | os.PathLike,
    b_mag_raw: np.ndarray,
    b_mag_cal: np.ndarray,
    t: np.ndarray,
    residuals: Optional[Mapping[str, np.ndarray]] = None,
    *,
    whitened: bool = False,
    title: str = "Magnetometer calibration",
    not_in_cost: Sequence[str] = (),
) -> Figure:
    """2×3 figure: field projections before/after, calibrated norm over time, residual histograms.

    Top row: xy, xz, yz projections of the raw field divided by its median norm and of the
    calibrated field D⁻¹(b_mag − o), with the unit circle. Bottom row: |field| over time (raw/median
    and calibrated, ideal 1) and per-channel residual histograms (x, y, z overlaid; with a standard
    normal density when `whitened`).

    Args:
        path: PNG destination.
        b_mag_raw: (N, 3) raw magnetometer, any unit; NaN rows are skipped.
        b_mag_cal: (N, 3) calibrated magnetometer, unit norm ideally.
        t: (N,) time, s.
        residuals: {"gyr"|"acc"|"mag": (M, 3)} residuals per channel, or None.
        whitened: residuals are divided by their noise standard deviation (dimensionless).
        title: figure title.
        not_in_cost: channels whose residual is reported but not in the model's cost — the accelerometer's
            gravity-only residual h − y when linear acceleration is modelled by keyframe velocities (the
            calibration's velocity model): it holds the linear acceleration, so it is drawn over its own range,
            without the N(0, 1) overlay, under a title that says so (not clipped into pile-ups at ±5).

    Returns:
        The Figure (already written to `path`).

    Raises:
        SessionError: arrays with the wrong shape (named by field).
    """
    path = Path(path)
    raw = _as_n3("b_mag_raw", b_mag_raw, path)
    cal = _as_n3("b_mag_cal", b_mag_cal, path, raw.shape[0])
    t = np.asarray(t, float)
    if t.shape != (raw.shape[0],):
        raise SessionError(str(path), "t", f"shape {t.shape}", f"({raw.shape[0]},)")
    ok = np.all(np.isfinite(raw), axis=1) & np.all(np.isfinite(cal), axis=1)
    ok_cal = ok
    if not ok.any():      # no row holds both: a lower-rate field whose calibrated rows are shifted by the magnetometer
        ok, ok_cal = np.all(np.isfinite(raw), axis=1), np.all(np.isfinite(cal), axis=1)   # lag (U22 #4): each its own
    raw_n = raw[ok] / np.median(np.linalg.norm(raw[ok], axis=1)) if ok.any() else raw[ok]

    fig = Figure(figsize=(15, 9), layout="constrained")
    grid = fig.add_gridspec(2, 3)
    for col, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
        _plot_projection(fig.add_subplot(grid[0, col]), raw_n, cal[ok_cal], i, j)
    _plot_norm(fig.add_subplot(grid[1, 0]), t[ok], raw_n, cal[ok_cal], t[ok_cal])
    _plot_residuals(fig, grid[1, 1:], residuals, whitened, tuple(not_in_cost))
    fig.suptitle(title)
    save_figure_atomic(fig, path)
    return fig


def _plot_projection(ax: Axes, raw_n: np.ndarray, cal: np.ndarray, i: int, j: int) -> None:
    idx = _subsample(raw_n.shape[0])
    ax.scatter(raw_n[idx, i], raw_n[idx, j], s=2, alpha=0.4, color="tab:gray", label="raw / median |raw|")
    idx = _subsample(cal.shape[0])      # the calibrated rows may be others than the raw ones (lag shift, U22 #4)
    ax.scatter(cal[idx, i], cal[idx, j], s=2, alpha=0.5, color="tab:blue", label="calibrated")
    phi = np.linspace(0.0, 2.0 * np.pi, 361)
    ax.plot(np.cos(phi), np.sin(phi), "k--", lw=1, label="unit circle")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"b_mag {_AXES[i]} [normalised]")
    ax.set_ylabel(f"b_mag {_AXES[j]} [normalised]")
    ax.set_title(f"Field projection {_AXES[i]}{_AXES[j]}")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=7, markerscale=4)


def _plot_norm(ax: Axes, t: np.ndarray, raw_n: np.ndarray, cal: np.ndarray, t_cal: np.ndarray | None = None) -> None:
    ax.plot(t, np.linalg.norm(raw_n, axis=1), color="tab:gray", lw=0.8, label="raw / median |raw|")
    ax.plot(t if t_cal is None else t_cal, np.linalg.norm(cal, axis=1), color="tab:blue", lw=0.8, label="calibrated")
    ax.axhline(1.0, color="k", ls="--", lw=1, label="ideal (1)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("|b_mag| [normalised]")
    ax.set_title("Field norm over time")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=7)


def _plot_residuals(fig: Figure, cell, residuals: Optional[Mapping[str, np.ndarray]],
                    whitened: bool, not_in_cost: tuple = ()) -> None:
    if not residuals:
        ax = fig.add_subplot(cell)
        ax.text(0.5, 0.5, "no residuals given", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return
    channels = [c for c in ("gyr", "acc", "mag") if c in residuals] + \
        [c for c in residuals if c not in ("gyr", "acc", "mag")]
    sub = cell.subgridspec(1, len(channels))
    for k, channel in enumerate(channels):
        ax = fig.add_subplot(sub[0, k])
        res = np.asarray(residuals[channel], float).reshape(-1, 3)
        res = res[np.all(np.isfinite(res), axis=1)]
        _histogram(ax, res, channel, whitened, channel in not_in_cost)


def _histogram(ax: Axes, res: np.ndarray, channel: str, whitened: bool, not_in_cost: bool = False) -> None:
    in_cost = whitened and not not_in_cost      # a whitened residual of the model: N(0, 1) ideally
    if res.shape[0] == 0:
        ax.text(0.5, 0.5, "no samples", ha="center", va="center", transform=ax.transAxes)
    else:
        lim = 5.0 if in_cost else max(float(np.percentile(np.abs(res), 99.5)), 1e-12)
        bins = np.linspace(-lim, lim, 61)
        for a in range(3):
            rms = float(np.sqrt(np.mean(res[:, a] ** 2)))
            ax.hist(np.clip(res[:, a], -lim, lim), bins=bins, density=True, histtype="step",
                    color=_COLORS[a], label=f"{_AXES[a]} (RMS {rms:.3g})")
        if in_cost:
            x = np.linspace(-lim, lim, 200)
            ax.plot(x, np.exp(-0.5 * x**2) / np.sqrt(2 * np.pi), "k--", lw=1, label="N(0, 1)")
        ax.legend(loc="upper right", fontsize=7)
    unit = "whitened [-]" if whitened else f"[{_UNITS.get(channel, 'unit')}]"
    ax.set_xlabel(f"{channel} residual {unit}")
    ax.set_ylabel("density")
    ax.grid(alpha=0.3)
    ax.set_title(f"{channel} residuals" if not not_in_cost else
                 f"{channel}: gravity-only residual, NOT in the cost\n(linear acceleration: velocity model)",
                 fontsize=None if not not_in_cost else 9)


def heading_deg(quat: np.ndarray) -> np.ndarray:
    """(N,) heading (yaw about nav z) of nRb quaternions (N, 4) w, x, y, z, in degrees (−180, 180]."""
    nRb = quat_to_rotmat(np.asarray(quat, float))
    return np.rad2deg(np.arctan2(nRb[:, 1, 0], nRb[:, 0, 0]))


def _break_wraps(y_deg: np.ndarray) -> np.ndarray:
    """Insert NaN where an angle wraps by more than 180° so that lines do not cross the plot."""
    y = np.asarray(y_deg, float).copy()
    jump = np.abs(np.diff(y)) > 180.0
    y[1:][jump] = np.nan
    return y


def plot_heading(
    path: str | os.PathLike,
    t: np.ndarray,
    quat_est: np.ndarray,
    quat_ref: Optional[np.ndarray] = None,
    *,
    title: str = "Heading",
    align: bool = False,
    mask: Optional[np.ndarray] = None,
    reference_label: str = "reference",
) -> Figure:
    """Heading over time, and the error against a reference when one is given.

    The error is taken from E = nRb_est · nRb_refᵀ (the nav-frame rotation from reference to
    estimate): its heading (yaw of E) and its total angle |Log E|, both in degrees.

    With `align`, the estimate is first aligned to the reference exactly as the console's orientation score
    does (`imugraph.evaluate.orientation_error`: the best time shift s and constant heading offset ψ over
    `mask`): nRb_est,k ← Rz(ψ) · nRb_est(k + s) (eq. 1). Without it a reference in another nav frame (BROAD's
    optical ENU vs the estimate's field-aligned frame) shows its frame offset as a ~90° "heading error"
    while the console reports 0.8°.

    Args:
        path: PNG destination.
        t: (N,) time, s.
        quat_est: (N, 4) estimated nRb, w, x, y, z.
        quat_ref: optional (N, 4) reference nRb (NaN rows where unknown).
        title: figure title.
        align: align the estimate to the reference first (above); unaligned when that cannot be scored.
        mask: (N,) bool, the samples the alignment and the error RMS use (e.g. Session.movement); None: all.
        reference_label: what the reference is ("truth", "reference [onboard AHRS]", ...), in the legend.

    Returns:
        The Figure (already written to `path`).

    Raises:
        SessionError: arrays with the wrong shape.
    """
    path = Path(path)
    t = np.asarray(t, float)
    q_est = np.asarray(quat_est, float)
    if t.ndim != 1 or q_est.shape != (t.shape[0], 4):
        raise SessionError(str(path), "quat_est", f"shape {q_est.shape} for t {t.shape}", "(N, 4)")
    rows = 1 if quat_ref is None else 2
    fig = Figure(figsize=(12, 3.5 * rows), layout="constrained")
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    note = ""
    if quat_ref is not None:
        q_ref = np.asarray(quat_ref, float)
        if q_ref.shape != q_est.shape:
            raise SessionError(str(path), "quat_ref", f"shape {q_ref.shape}", f"{q_est.shape}")
        if align:
            q_est, note = _aligned_estimate(q_est, q_ref, mask)
    axes[0].plot(t, _break_wraps(heading_deg(q_est)), color="tab:blue", lw=1,
                 label="estimate" + (" (aligned)" if note else ""))
    if quat_ref is not None:
        known = np.all(np.isfinite(q_ref), axis=1)
        axes[0].plot(t[known], _break_wraps(heading_deg(q_ref[known])), color="k", lw=1, ls="--",
                     label=reference_label)
        ok = known & np.all(np.isfinite(q_est), axis=1)
        scored = ok if mask is None else ok & np.asarray(mask, bool).reshape(-1)
        _plot_heading_error(axes[1], t[ok], q_est[ok], q_ref[ok], scored[ok] if scored[ok].any() else None)
        axes[1].set_title(f"Error against the {reference_label}" + (f"\n({note})" if note else ""),
                          fontsize=9 if note else None)
    axes[0].set_ylabel("heading [deg]")
    axes[0].set_ylim(-185, 185)
    axes[0].set_title(title)
    axes[0].grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    save_figure_atomic(fig, path)
    return fig


def _aligned_estimate(q_est: np.ndarray, q_ref: np.ndarray, mask: Optional[np.ndarray]) -> tuple[np.ndarray, str]:
    """(Rz(ψ) · q_est(k + s) (N, 4), NaN where k + s is outside the record; a note naming ψ and s) at the
    alignment of `imugraph.evaluate.orientation_error`; (q_est, "") when that cannot be scored."""
    from imugraph.errors import ImugraphError
    from imugraph.evaluate import orientation_error, shift_quat

    try:
        score = orientation_error(q_est, q_ref, mask, 1.0)      # rate 1: shift_s is then in samples
    except ImugraphError:
        return q_est, ""
    n, s, psi = q_est.shape[0], float(score.shift_samples), np.deg2rad(score.heading_offset_deg)
    k = np.arange(n)
    inside = (k + s >= 0) & (k + s <= n - 1) & np.all(np.isfinite(q_est), axis=1)
    inside[inside] &= np.all(np.isfinite(q_est[np.clip(np.ceil(k[inside] + s).astype(int), 0, n - 1)]), axis=1)
    out = np.full_like(q_est, np.nan)
    c, si = np.cos(psi), np.sin(psi)
    Rz = np.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]])
    out[inside] = rotmat_to_quat(Rz @ quat_to_rotmat(shift_quat(q_est, k[inside], s)))   # (eq. 1)
    return out, f"aligned as the console score: heading offset {score.heading_offset_deg:+.2f}°, shift {s:+.2f} samples"


def _plot_heading_error(ax: Axes, t: np.ndarray, q_est: np.ndarray, q_ref: np.ndarray,
                        scored: Optional[np.ndarray] = None) -> None:
    """Heading and total error over time; the legend's RMS over `scored` (None: every sample)."""
    E = quat_to_rotmat(q_est) @ np.swapaxes(quat_to_rotmat(q_ref), -1, -2)
    yaw = np.rad2deg(np.arctan2(E[:, 1, 0], E[:, 0, 0]))
    total = np.rad2deg(np.linalg.norm(quat_to_rotvec(rotmat_to_quat(E)), axis=1))
    sel = np.ones(yaw.shape, bool) if scored is None else scored
    rms = float(np.sqrt(np.mean(yaw[sel]**2))) if sel.any() else float("nan")
    rms_total = float(np.sqrt(np.mean(total[sel]**2))) if sel.any() else float("nan")
    where = "" if scored is None else " over the scored samples"
    ax.plot(t, _break_wraps(yaw), color="tab:red", lw=1, label=f"heading error (RMS {rms:.2f}°{where})")
    ax.plot(t, total, color="tab:gray", lw=1, label=f"total orientation error (RMS {rms_total:.2f}°{where})")
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_ylabel("error [deg]")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
