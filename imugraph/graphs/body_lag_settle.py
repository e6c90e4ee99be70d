"""How long the fixed lag's batch bootstrap must be: until the placements it hands on have settled (helper L22).

The fixed lag holds (anchored bootstrap) or starts from (BodyOptions.lag_bootstrap_marginal) the sensor-to-segment
rotations bRs of its batch bootstrap. The motion criterion (A1) of imugraph.graphs.body_bootstrap ends the bootstrap
once every sensor has moved "enough", a fixed amount; on CMU 131_02 (auto: 5.1 s) the shoulder's bRs is still off by
≈ 0.7° there (benchmarks/l22_lag_diag.py), which the Cardan columns of (E1) amplify near 90° abduction (one 1 s window
of 131_02 seed 1: geodesic 0.81° → 12.6° RMS over the columns). (A2), BodyOptions.lag_bootstrap_settle_deg: starting
at (A1)'s end, the bootstrap is solved again every `step_s` seconds longer until, for EVERY sensor,

    |Log(bR̂s(t − step)ᵀ bR̂s(t))| < settle_deg                                                            (A2)

(or max_s is reached), and the bootstrap ends at that t. Only the IMU data up to t are used (the stream starts there),
so it stays causal; the price is a later start of the stream and one batch solve per step.
"""

from __future__ import annotations

import numpy as np


def _angle_deg(R: np.ndarray) -> float:
    return float(np.rad2deg(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def settled_bootstrap_s(solve_placements, start_s: float, end_s: float, settle_deg: float, step_s: float = 1.0,
                        max_s: float = 30.0) -> tuple[float, dict]:
    """(bootstrap length, details) by (A2) (module docstring).

    Args:
        solve_placements: t ↦ {sensed segment: (bRs, b_pos)} of a batch bootstrap of length t (s from the start).
        start_s: (A1)'s length; end_s: the session's length (the bootstrap never reaches it); settle_deg, step_s,
            max_s: as in (A2).
    """
    t, prev, changes = float(start_s), None, []
    stop = min(float(max_s), float(end_s) - step_s)
    while True:
        place = solve_placements(t)
        if prev is not None:
            changes.append(max(_angle_deg(prev[n][0].T @ place[n][0]) for n in place))                  # (A2)
            if changes[-1] < settle_deg:
                break
        if t + step_s > stop:
            break
        prev, t = place, t + step_s
    return t, {"settle_deg": settle_deg, "settle_changes_deg": changes, "settled": bool(changes and changes[-1] < settle_deg),
               "settle_solves": len(changes) + 1}
