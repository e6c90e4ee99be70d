"""Ramped window edges for windowed effects (issue 5, S15 (R1); used by magnetic_disturbance when its
`RAMPS` flag is on).

A magnet brought to the sensor by hand does not appear in one sample: its field rises over the time the
hand moves it (BROAD 32/34/36: the magnet attached and taken off by hand; the harness injects raised-
cosine ramps of 0.2–1.0 s). A step envelope leaves, on each held-out ramp, a residual up to half the
window's field (harness case 001, sim00 + 23.5 µT-equivalent, 0.85 s ramps: whitened RMS 2.3/6.6/5.1 over
the rising ramp, 2.1/6.6/4.4 over the falling one, ≈ 1 elsewhere in the window). The envelope of window
w is instead

    e_w(t) = clip((t − c_a)/w_a + ½, 0, 1) · clip((c_b − t)/w_b + ½, 0, 1)                         (R1)

(linear ramps of width w_a, w_b centred on c_a, c_b; w = 0 is the step; an edge with less than MIN_SIDE_S
of the recording on either side — the recording's end, a neighbouring window — keeps the step), and the window's field is
e_w(t)·(Δo_w + D bRn Δn_w) (M1). A linear ramp is the least-assuming shape between "off" and "on" with one
parameter for its duration: it is NOT the injection's raised cosine (largest difference 0.07 of the field).

Each edge (centre, width) is located like the window's edges themselves (`base.refine_edge`, all samples:
localisation, as in docs/diagnose.md §3): least squares of the whitened residual x_j (3 axes) on
α + β e(t_j) over ±EDGE_SPAN_S around the edge, for every centre within ±CENTRE_SPAN_S (steps of one sample
or 10 ms) and width 0…MAX_RAMP_S (steps of 50 ms), closed form per grid point:

    SSE(c, w) = S_xx − ‖S_xe‖² / S_ee,   S_xe = Σ_j (x_j − x̄)(e_j − ē),  S_ee = Σ_j (e_j − ē)²          (R2)

The fields Δo_w, Δn_w are then estimated on training samples only, as before; one more parameter per edge
is counted in n_params (its width; its centre is the window's edge, already counted). The residual the
edges are located on is the base fit's with the step model's δo, δD removed (magnetic_disturbance.fit).
"""

from __future__ import annotations

import numpy as np

EDGE_SPAN_S = 1.5          # samples within this of an edge are used to locate its ramp
CENTRE_SPAN_S = 0.5        # the ramp's centre is searched within this of the step edge
MAX_RAMP_S = 1.5           # longest ramp (a hand bringing a magnet: ≈ 1 s)
WIDTH_STEP_S = 0.05
MIN_SIDE_S = 0.75          # an edge is given a ramp only with this much of the recording on both of its sides


def ramp(t: np.ndarray, centre: float, width: float, rising: bool) -> np.ndarray:
    """(N,) linear ramp 0 → 1 (rising) or 1 → 0 centred on `centre`, `width` s long (0: a step) (R1)."""
    if width <= 0:
        e = (t >= centre).astype(float)
    else:
        e = np.clip((t - centre) / width + 0.5, 0.0, 1.0)
    return e if rising else 1.0 - e


def envelope(t: np.ndarray, edges: dict) -> np.ndarray:
    """(N,) envelope e_w (R1) of one window from its located edges {"start": (c_a, w_a), "end": (c_b, w_b)}."""
    return ramp(t, *edges["start"], rising=True) * ramp(t, *edges["end"], rising=False)


def locate_edge(t: np.ndarray, z: np.ndarray, edge_t: float, rising: bool, lo: float, hi: float) -> tuple:
    """(centre, width) of one edge by (R2): z (N, 3) the whitened residual, edge_t the step edge, [lo, hi]
    the time span the edge may use (the window's other half and other windows excluded)."""
    a, b = max(lo, edge_t - EDGE_SPAN_S), min(hi, edge_t + EDGE_SPAN_S)
    if min(edge_t - a, b - edge_t) < MIN_SIDE_S:     # no room on one side (the recording's end, a neighbouring
        return float(edge_t), 0.0                     # window): a ramp is not identifiable, the step stays
    m = (t >= a) & (t <= b) & np.all(np.isfinite(z), axis=1)
    tt, x = t[m], z[m]
    if len(tt) < 10:
        return float(edge_t), 0.0
    dt = float(np.median(np.diff(tt)))
    step = max(dt, 0.01)
    centres = np.arange(edge_t - CENTRE_SPAN_S, edge_t + CENTRE_SPAN_S + 1e-9, step)
    widths = np.arange(0.0, MAX_RAMP_S + 1e-9, WIDTH_STEP_S)
    C, W = np.meshgrid(centres, widths, indexing="ij")
    C, W = C.ravel(), W.ravel()
    u = (tt[None, :] - C[:, None]) / np.maximum(W[:, None], 1e-12) + 0.5
    E = np.where(W[:, None] > 0, np.clip(u, 0.0, 1.0), (tt[None, :] >= C[:, None]).astype(float))
    if not rising:
        E = 1.0 - E
    Ec = E - E.mean(axis=1, keepdims=True)
    xc = x - x.mean(axis=0)
    Sxe = Ec @ xc                                                                      # (G, 3)
    See = np.sum(Ec**2, axis=1)
    gain = np.where(See > 1e-12, np.sum(Sxe**2, axis=1) / np.maximum(See, 1e-12), -np.inf)   # (R2)
    k = int(np.argmax(gain))
    return float(C[k]), float(W[k])


def locate_ramps(t: np.ndarray, r: np.ndarray, sigma, windows: list) -> list:
    """Per window (t_start, t_end): {"start": (c_a, w_a), "end": (c_b, w_b)} by (R2) on the residual r
    (N, 3) whitened by sigma; each edge searched within its own half of the window and away from the
    neighbouring windows."""
    z = np.asarray(r, float) / np.asarray(sigma, float)
    out = []
    bounds = sorted(windows)
    for a, b in windows:
        mid = 0.5 * (a + b)
        prev_end = max([w[1] for w in bounds if w[1] <= a] or [-np.inf])
        next_start = min([w[0] for w in bounds if w[0] >= b] or [np.inf])
        start = locate_edge(t, z, a, True, 0.5 * (prev_end + a) if np.isfinite(prev_end) else -np.inf, mid)
        end = locate_edge(t, z, b, False, mid, 0.5 * (b + next_start) if np.isfinite(next_start) else np.inf)
        out.append({"start": start, "end": end})
    return out
