"""The short result tables the commands print on stdout.

Units: D and o in the magnetometer's unit (D maps the unit-norm field to it), dip in degrees, gyro bias
in °/s (stored in rad/s), noise as per-axis standard deviations (gyr rad/s, acc m/s², mag its unit).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np

from imugraph.calibration.result import Calibration
from imugraph.commands.common import Scores

if TYPE_CHECKING:
    from imugraph.sim.scenario import Truth

LABEL = 16   # width of the label column
SLOT = 34    # width of one vec() column plus its separator


def vec(values: Sequence[float], fmt: str = "9.3f") -> str:
    """A vector as '[ a  b  c ]' with a fixed number format; NaN prints as 'nan'."""
    return "[" + " ".join(format(float(v), fmt) for v in np.asarray(values, float).reshape(-1)) + " ]"


def _row(label: str, text: str) -> str:
    return f"  {label:<{LABEL}}{text}"


def _std(cal: Calibration, key: str, shape: tuple) -> np.ndarray:
    value = cal.std.get(key) if isinstance(cal.std, dict) else None
    return np.full(shape, np.nan) if value is None else np.asarray(value, float).reshape(shape)


def _coverage_line(coverage: dict) -> Optional[str]:
    if not isinstance(coverage, dict) or "identifiable" not in coverage:
        return None
    problems = coverage.get("problems") or []
    text = "yes" if coverage["identifiable"] else "NO"
    return _row("identifiable", text + (f" ({'; '.join(map(str, problems))})" if problems else ""))


def _percent(value: float, fmt: str) -> str:
    """A fraction as a percentage, or 'n/a' (same width) when it could not be computed (NaN)."""
    return format(100 * value, fmt) + " %" if np.isfinite(value) else format("n/a", f">{fmt.split('.')[0]}") + "  "


def score_lines(scores: Scores) -> list[str]:
    """Field-norm errors before/after (percent; n/a when not computable) and the orientation error vs the
    session's quat: "vs truth", or "vs reference (<source>)" when it is a device's own estimate (Scores.reference)."""
    lines = [_row("field norm RMS", f"before {_percent(scores.norm_before, '7.2f')}   "
                                    f"after {_percent(scores.norm_after, '7.3f')}")]
    if scores.orientation_rms_deg is not None:
        lines.append(_row("orientation", f"RMS {scores.orientation_rms_deg:.2f}° vs {scores.reference} "
                          "(best heading offset and time shift removed)"))
    return lines


def calibration_table(cal: Calibration, scores: Scores, title: str) -> str:
    """The calibrate command's table: D rows, o, dip, gyro bias, gyro scale/misalignment E (%), noise,
    marginal std, loop state, scores.

    Args:
        cal: imugraph.calibration.result.Calibration.
        scores: field-norm and orientation scores.
        title: first line.

    Returns:
        Multi-line text without a trailing newline.
    """
    std_D, std_o = _std(cal, "D", (3, 3)), _std(cal, "o", (3,))
    std_b = np.rad2deg(_std(cal, "gyro_bias", (3,)))
    lines = [title]
    for i in range(3):
        lines.append(_row("D" if i == 0 else "", f"{vec(cal.D[i])}  ± {vec(std_D[i], '7.4f')}"))
    lines.append(_row("o", f"{vec(cal.o)}  ± {vec(std_o, '7.4f')}"))
    std_dip = cal.std.get("dip_deg") if isinstance(cal.std, dict) else None
    lines.append(_row("dip", f"{cal.dip_deg:.3f}°" + ("" if std_dip is None else f"  ± {float(std_dip):.3f}°")))
    lines.append(_row("gyro bias °/s", f"{vec(np.rad2deg(cal.gyro_bias), '9.4f')}  ± {vec(std_b, '7.4f')}"))
    E = np.asarray(cal.gyro_map, float)          # ω = (I + E)·b_gyr − b (calibration/gyro_map.py)
    if np.any(E):
        for i in range(3):
            lines.append(_row("gyro map E %" if i == 0 else "", vec(100.0 * E[i], "9.4f")))
    else:
        lines.append(_row("gyro map E", "not estimated (too few turns, or did not settle; see info)"))
    units = {"gyr": "rad/s", "acc": "m/s²", "mag": "mag unit"}
    for key, unit in units.items():
        if key in cal.noise:
            lines.append(_row(f"noise {key}", f"{vec(cal.noise[key], '9.5f')}  {unit}"))
    lines.append(_row("converged", f"{'yes' if cal.converged else 'NO'} after {cal.iterations} ML rounds"))
    cov = _coverage_line(cal.coverage)
    if cov:
        lines.append(cov)
    return "\n".join(lines + score_lines(scores))


def comparison_table(cal: Calibration, truth: "Truth", scores: Scores, title: str) -> str:
    """The demo's before/after table: true vs estimated D, o, dip, gyro bias with the reported std.

    Args:
        cal: estimated Calibration.
        truth: imugraph.sim.scenario.Truth (D, o, dip_deg, gyro_bias rad/s, field_norm).
        scores: field-norm errors before/after and orientation error vs the simulated truth.
        title: first line.

    Returns:
        Multi-line text without a trailing newline.
    """
    std_D, std_o = _std(cal, "D", (3, 3)), _std(cal, "o", (3,))
    std_b = np.rad2deg(_std(cal, "gyro_bias", (3,)))
    head = f"  {'':<{LABEL}}{'true':<{SLOT}}{'estimated':<{SLOT}}± std"
    lines = [title, head]
    for i in range(3):
        lines.append(_row(f"D row {i + 1}", f"{vec(truth.D[i])}  {vec(cal.D[i])}  {vec(std_D[i], '7.4f')}"))
    lines.append(_row("o", f"{vec(truth.o)}  {vec(cal.o)}  {vec(std_o, '7.4f')}"))
    std_dip = cal.std.get("dip_deg", np.nan) if isinstance(cal.std, dict) else np.nan
    dip = [f" {truth.dip_deg:9.3f}", f" {cal.dip_deg:9.3f}"]
    lines.append(_row("dip °", f"{dip[0]:<{SLOT}}{dip[1]:<{SLOT}}  {float(std_dip):7.4f}"))
    lines.append(_row("gyro bias °/s", f"{vec(np.rad2deg(truth.gyro_bias), '9.4f')}  "
                      f"{vec(np.rad2deg(cal.gyro_bias), '9.4f')}  {vec(std_b, '7.4f')}"))
    rel_D = np.linalg.norm(cal.D - truth.D) / np.linalg.norm(truth.D)
    err_o = np.linalg.norm(cal.o - truth.o) / truth.field_norm
    lines.append(_row("error", f"‖ΔD‖/‖D‖ {100 * rel_D:.3f} %   ‖Δo‖/field {100 * err_o:.3f} %   "
                      f"Δdip {cal.dip_deg - truth.dip_deg:+.3f}°"))
    lines.append(_row("converged", f"{'yes' if cal.converged else 'NO'} after {cal.iterations} ML rounds"))
    return "\n".join(lines + score_lines(scores))
