"""Accelerometer scale, skew and offset from quasi-static samples (an accelerometer ellipsoid fit).

Model (a constant calibration error of the accelerometer; f the true specific force, body frame):

    b_acc = Ka·f + ba + e        ⇒   f̂ = T·(b_acc − ba),   T = I + S,  S = Sᵀ          [acc map]

When the sensor is quasi-static, |f| = g, so the samples lie on the ellipsoid

    ‖(I + S)(y_i − ba)‖ = g                                                               [ellipsoid]

(y_i: window means of b_acc; the same algebra as the magnetometer's ellipsoid, Kok et al. 2012 step 1,
with a known radius g). 9 unknowns: the 6 entries of the symmetric S (per-axis scale and the
non-orthogonality of the axes) and the offset ba. Ka = T⁻¹·Q for ANY rotation Q: the ellipsoid cannot
see a rotation of the accelerometer axes (its misalignment to the gyro axes) — only a rotation-aware
reference (the gyro, an optical truth) can. The isotropic part of S is tied to the g given (default
G_NOMINAL); the smoother re-estimates g, so it only fixes the units.

Quasi-static windows: non-overlapping windows of `window_s` whose mean rate is below `max_rate` (the
centripetal ω²r at a 0.1 m lever arm stays below 0.01 m/s²), whose accelerometer and gyro scatter are
at the noise level and whose mean |b_acc| is within `max_dev` of g. Windows are merged per direction
cell (`cell_deg`), so a long rest counts as ONE orientation; the fit weighs every cell alike (robust
soft-ℓ1 loss against a moving hand that passes the window tests).

Coverage gate (named): at least MIN_CELLS distinct orientations, the smallest eigenvalue of the
directions' second moment (1/3 for a uniform sphere, 0 for one axis) at least MIN_SPREAD, and the fit's
standard deviations (Gauss–Newton covariance × residual variance, cells taken as independent) below
MAX_SCALE_STD and MAX_OFFSET_STD, and a plausible map (|S| ≤ MAX_ABS_S, |ba| ≤ MAX_ABS_OFFSET, norm residual RMS
≤ MAX_RMS: a small cap of orientations fits a huge sphere almost as well). Otherwise `AccMapError` says which test
failed and by how much.

BROAD (H10, benchmarks/h10_acc_map.py; optical truth as a diagnostic only): every trial rests in one orientation
(z up within 2.5°), so the gate fires on all 17. The same unit's |b_acc| at rest is 9.818 (02, 07, 16) to 9.903
m/s² (06) — 06 vs 16: 0.085 m/s² at directions 3.6° apart, which a constant map could only give with ≈ 7 % skew
or a 1.3 m/s² offset: the accelerometer's z reading moves by ≈ 0.8 % between recordings, so a map fitted on other
recordings does not carry over. Optical fits per trial (scale/skew 0.0–0.4 %, offsets ≤ 0.04 m/s² where well
determined) applied before calibrate do not close 06/15/16 (README, issue 2c H10); not used by calibrate.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from imugraph.errors import CalibrationError

G_NOMINAL = 9.81          # m/s²: the radius of the sphere (units only; the smoother re-estimates g)
MIN_CELLS = 12            # distinct orientations (direction cells)
MIN_SPREAD = 0.04         # smallest eigenvalue of mean(u uᵀ) over the cells (uniform sphere 1/3)
MAX_SCALE_STD = 0.002     # std of each entry of S (0.2 %)
MAX_OFFSET_STD = 0.02     # std of each entry of ba, m/s²
MAX_ABS_S = 0.05          # plausible |S_ij| (5 %): a larger fit is a small cap of a huge sphere, not a calibration
MAX_ABS_OFFSET = 1.0      # plausible |ba_i|, m/s² (0.1 g)
MAX_RMS = 0.05            # m/s²: RMS of ‖f̂‖ − g over the cells; above, the windows were not quasi-static
_IDX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))   # the 6 entries of S in the parameter vector


class AccMapError(CalibrationError):
    """The quasi-static samples do not determine the accelerometer map (too few orientations, …)."""


@dataclass
class AccMap:
    """f̂ = (I + S)(b_acc − ba).

    Attributes:
        S: (3, 3) symmetric scale/skew correction (dimensionless).
        ba: (3,) offset, m/s².
        std_S: (3, 3) standard deviations of S's entries.
        std_ba: (3,) standard deviations of ba, m/s².
        rms: RMS of the fitted norm residual ‖f̂‖ − g over the cells, m/s² (raw: `rms_raw`, with S = 0, ba = 0).
        n_windows, n_cells: quasi-static windows found and direction cells fitted.
        spread: smallest eigenvalue of the cells' direction second moment.
        g: the sphere's radius used, m/s².
    """

    S: np.ndarray
    ba: np.ndarray
    std_S: np.ndarray
    std_ba: np.ndarray
    rms: float
    rms_raw: float
    n_windows: int
    n_cells: int
    spread: float
    g: float = G_NOMINAL
    info: dict = field(default_factory=dict)

    def apply(self, b_acc: np.ndarray) -> np.ndarray:
        """(N, 3) corrected specific force f̂ = (I + S)(b_acc − ba)."""
        return (np.asarray(b_acc, float) - self.ba) @ (np.eye(3) + self.S).T

    def to_json(self) -> dict:
        """The calibration.json block proposed for `acc_map` (lists, m/s² and dimensionless)."""
        return {"S": self.S.tolist(), "ba": self.ba.tolist(), "std_S": self.std_S.tolist(),
                "std_ba": self.std_ba.tolist(), "g": self.g, "rms": self.rms, "n_cells": self.n_cells,
                "spread": self.spread, "model": "f = (I + S)(b_acc - ba), S symmetric"}


def quasi_static_windows(acc: np.ndarray, gyr: np.ndarray, rate: float, window_s: float = 0.2,
                         max_rate: float = 0.3, max_acc_std: float = 0.15, max_gyr_std: float = 0.05,
                         max_dev: float = 0.5, g: float = G_NOMINAL) -> np.ndarray:
    """(M, 3) mean b_acc of the quasi-static windows (see the module docstring; thresholds in SI units:
    rad/s, m/s²; the acc/gyro scatter is the root of the summed per-axis variances within the window)."""
    acc, gyr = np.asarray(acc, float), np.asarray(gyr, float)
    n = max(3, int(round(window_s * rate)))
    m = acc.shape[0] // n
    if m == 0:
        return np.zeros((0, 3))
    a = acc[: m * n].reshape(m, n, 3)
    w = gyr[: m * n].reshape(m, n, 3)
    a_mean, w_mean = a.mean(axis=1), w.mean(axis=1)
    ok = (np.linalg.norm(w_mean, axis=1) < max_rate)
    ok &= np.sqrt(a.var(axis=1).sum(axis=1)) < max_acc_std
    ok &= np.sqrt(w.var(axis=1).sum(axis=1)) < max_gyr_std
    ok &= np.abs(np.linalg.norm(a_mean, axis=1) - g) < max_dev
    ok &= np.all(np.isfinite(a_mean), axis=1) & np.all(np.isfinite(w_mean), axis=1)
    return a_mean[ok]


def direction_cells(y: np.ndarray, cell_deg: float = 5.0) -> np.ndarray:
    """(C, 3) mean of the windows y per direction cell (a cube grid on the unit direction, ≈ cell_deg wide)."""
    if len(y) == 0:
        return np.zeros((0, 3))
    u = y / np.linalg.norm(y, axis=1, keepdims=True)
    key = np.round(u / np.radians(cell_deg)).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    sums = np.zeros((inv.max() + 1, 3))
    np.add.at(sums, inv, y)
    return sums / np.bincount(inv)[:, None]


def _unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    S = np.zeros((3, 3))
    for k, (i, j) in enumerate(_IDX):
        S[i, j] = S[j, i] = p[k]
    return S, p[6:9]


def residual_jacobian(p: np.ndarray, y: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    """r_i = ‖(I + S)(y_i − ba)‖ − g and its (M, 9) Jacobian in p = (S00 S11 S22 S01 S02 S12, ba)."""
    S, ba = _unpack(p)
    d = y - ba
    z = d @ (np.eye(3) + S).T
    nz = np.linalg.norm(z, axis=1)
    u = z / nz[:, None]
    J = np.empty((len(y), 9))
    for k, (i, j) in enumerate(_IDX):   # ∂z/∂S_ij = e_i d_j (+ e_j d_i off the diagonal)
        J[:, k] = u[:, i] * d[:, j] + (u[:, j] * d[:, i] if i != j else 0.0)
    J[:, 6:9] = -u @ (np.eye(3) + S)
    return nz - g, J


def fit_acc_map(y: np.ndarray, g: float = G_NOMINAL, cell_deg: float = 5.0, source: str = "<session>",
                gate: bool = True) -> AccMap:
    """Fit S, ba to quasi-static window means y (M, 3) (robust Gauss–Newton over the direction cells).

    Raises:
        AccMapError: too few orientations (cells or spread) or a fit whose std exceeds the limits, named.
    """
    from scipy.optimize import least_squares

    y = np.asarray(y, float)
    cells = direction_cells(y, cell_deg)
    u = cells / np.linalg.norm(cells, axis=1, keepdims=True) if len(cells) else np.zeros((0, 3))
    spread = float(np.linalg.eigvalsh(u.T @ u / len(u))[0]) if len(u) else 0.0
    where = f"{source}: field 'acc'"
    if gate and len(cells) < MIN_CELLS:
        raise AccMapError(f"{where}: found quasi-static samples in {len(cells)} orientations ({len(y)} windows); "
                          f"expected at least {MIN_CELLS} distinct orientations to fit the accelerometer map "
                          "(hold the sensor still in several orientations covering all axes)")
    if gate and spread < MIN_SPREAD:
        raise AccMapError(f"{where}: found quasi-static orientations spread {spread:.3f} (smallest eigenvalue of "
                          f"their directions' second moment); expected at least {MIN_SPREAD} — the orientations "
                          "hold gravity about too few body axes (rest in orientations covering all axes)")
    if len(cells) < 10:
        raise AccMapError(f"{where}: found {len(cells)} quasi-static orientations; expected at least 10 (9 unknowns)")
    lim = np.r_[np.full(6, 2 * MAX_ABS_S), np.full(3, 2 * MAX_ABS_OFFSET)]   # bounds keep a degenerate cap finite
    sol = least_squares(lambda p: residual_jacobian(p, cells, g)[0], np.zeros(9),
                        jac=lambda p: residual_jacobian(p, cells, g)[1], loss="soft_l1", f_scale=0.05,
                        bounds=(-lim, lim))
    r, J = residual_jacobian(sol.x, cells, g)
    dof = max(len(cells) - 9, 1)
    cov = np.linalg.pinv(J.T @ J) * float(r @ r) / dof
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    S, ba = _unpack(sol.x)
    std_S, std_ba = _unpack(std)
    r0 = np.linalg.norm(cells, axis=1) - g
    out = AccMap(S=S, ba=ba, std_S=std_S, std_ba=std_ba, rms=float(np.sqrt(np.mean(r ** 2))),
                 rms_raw=float(np.sqrt(np.mean(r0 ** 2))), n_windows=len(y), n_cells=len(cells), spread=spread,
                 g=g, info={"cond": float(np.linalg.cond(J))})
    if gate and (np.abs(S).max() > MAX_ABS_S or np.abs(ba).max() > MAX_ABS_OFFSET or out.rms > MAX_RMS):
        raise AccMapError(f"{where}: found an implausible accelerometer map (max |S| {100 * np.abs(S).max():.1f} %, "
                          f"max |ba| {np.abs(ba).max():.2f} m/s², norm residual RMS {out.rms:.3f} m/s²); expected "
                          f"|S| ≤ {100 * MAX_ABS_S:.0f} %, |ba| ≤ {MAX_ABS_OFFSET} m/s², RMS ≤ {MAX_RMS} m/s² "
                          "(the windows are not quasi-static, or cover only a small cap of orientations)")
    if gate and (std_S.max() > MAX_SCALE_STD or std_ba.max() > MAX_OFFSET_STD):
        raise AccMapError(f"{where}: found accelerometer map std {100 * std_S.max():.2f} % (scale/skew), "
                          f"{std_ba.max():.3f} m/s² (offset); expected at most {100 * MAX_SCALE_STD:.2f} % and "
                          f"{MAX_OFFSET_STD} m/s² (too few or too scattered quasi-static orientations)")
    return out


def session_acc_map(session, **window_kw) -> AccMap:
    """The accelerometer map of a Session from its own quasi-static windows (gated; AccMapError when not)."""
    y = quasi_static_windows(session.acc, session.gyr, session.rate, **window_kw)
    return fit_acc_map(y, source=str(getattr(session, "source", "<session>")))


def map_session(session, acc_map: AccMap | None = None):
    """(session with acc replaced by f̂, info dict). With acc_map None the map is fitted on the session; when
    its gate fails the session is returned unchanged and info["acc_map_gate"] holds the named reason."""
    if acc_map is None:
        try:
            acc_map = session_acc_map(session)
        except AccMapError as exc:
            return session, {"acc_map_gate": str(exc)}
    return replace(session, acc=acc_map.apply(session.acc)), {"acc_map": acc_map.to_json()}
