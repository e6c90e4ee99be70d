"""The calibration record written to `calibration.json` (DESIGN.md contract)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def n_mag_from_dip(dip_rad: float) -> np.ndarray:
    """Nav-frame unit field: x along the horizontal component, z up: [cos δ, 0, −sin δ]."""
    return np.array([np.cos(dip_rad), 0.0, -np.sin(dip_rad)])


NOMINAL_VELOCITY_PROCESS = (0.5, 2.0)    # σ_v m/s, τ_v s when a calibration carries no estimate


@dataclass
class Calibration:
    """Magnetometer model b_mag = D·bRn·n_mag + o + e (Kok & Schön), plus gyro bias and noise levels.

    Attributes:
        D: (3, 3) scale, skew, soft iron and misalignment to the inertial axes.
        o: (3,) hard-iron offset, in the magnetometer's unit.
        dip_deg: field dip δ in degrees (positive: field points down).
        gyro_bias: (3,) rad/s.
        noise: per-axis standard deviations {"gyr": rad/s, "acc": m/s², "mag": magnetometer unit}.
        std: marginal standard deviations {"D": (3, 3), "o": (3,)}.
        coverage: what rotation the data hold and whether the problem was identifiable.
        converged, iterations: state of the maximum-likelihood loop.
        mag_delay_s: lag of the magnetometer behind the gyroscope, s (applied before the calibration:
            `imugraph.calibration.alignment.undelay_magnetometer`).
        disturbances: lasting disturbances found (`imugraph.calibration.disturbance`): a list of
            {"t_start", "t_end" (s), "offset" (3, raw unit, or None), "modelled", "left_out"}; `corrected` applies
            them as the calibration's own solve did (disturbance.apply_windows). left_out (optional, [] when absent):
            [[t_a, t_b], ...] s inclusive, rows of a modelled window the solve left out (Options.window_trial_verdict:
            the margins before a magnet arrives).
        gyro_map: (3, 3) gyro scale/misalignment E (`imugraph.calibration.gyro_map`): the rate is
            ω = (I + E)·b_gyr − gyro_bias; zero when not estimated. `corrected_gyro` applies it.
        acc_lead_samples: δ, accelerometer row j paired with the strapdown orientation of row j + δ
            (`imugraph.calibration.acc_timing`; a setting of the sensor, recorded so that smoothing with
            this calibration pairs the rows the same way).
        velocity_sigma, velocity_tau: σ_v (m/s) and τ_v (s) of the sensor's velocity process as the ML loop
            estimated them (`imugraph.calibration.velocity_process`), None when not estimated or per axis;
            smoothing with this calibration uses them.
    """

    D: np.ndarray
    o: np.ndarray
    dip_deg: float
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    noise: dict = field(default_factory=dict)
    std: dict = field(default_factory=dict)
    coverage: dict = field(default_factory=dict)
    converged: bool = False
    iterations: int = 0
    mag_delay_s: float = 0.0
    disturbances: list = field(default_factory=list)
    gyro_map: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    acc_lead_samples: float = 0.0
    velocity_sigma: float | None = None
    velocity_tau: float | None = None

    @property
    def dip_rad(self) -> float:
        return float(np.deg2rad(self.dip_deg))

    @property
    def n_mag(self) -> np.ndarray:
        return n_mag_from_dip(self.dip_rad)

    def velocity_process(self, sigma: float | None = None, tau: float | None = None) -> tuple[float, float]:
        """σ_v (m/s), τ_v (s) for smoothing with this calibration: the values given, else its estimate, else the
        nominal bounded-velocity process (NOMINAL_VELOCITY_PROCESS: a hand-held or body-worn sensor)."""
        return (sigma if sigma is not None else (self.velocity_sigma or NOMINAL_VELOCITY_PROCESS[0]),
                tau if tau is not None else (self.velocity_tau or NOMINAL_VELOCITY_PROCESS[1]))

    def apply(self, b_mag: np.ndarray) -> np.ndarray:
        """Calibrated field D⁻¹(b_mag − o): unit norm, in the inertial sensor axes. (N, 3) → (N, 3)."""
        return np.linalg.solve(self.D, (np.asarray(b_mag, float) - self.o).T).T

    def calibrated_field(self, t: np.ndarray, b_mag: np.ndarray) -> np.ndarray:
        """The model's calibrated field D⁻¹(y − o), (N, 3) → (N, 3): y = `corrected(t, b_mag)` when there are
        disturbance windows, else b_mag itself: the field the "after" field-norm score and calibration.png show."""
        return self.apply(self.corrected(t, b_mag) if self.disturbances else b_mag)

    def corrected(self, t: np.ndarray, b_mag: np.ndarray) -> np.ndarray:
        """The raw field on the gyro's time base with the disturbance windows applied: the lag removed,
        modelled offsets subtracted, unexplained windows and a modelled window's left_out runs set to NaN (no
        sample): y_j − Δo_w for j ∈ w modelled, weight 0 elsewhere in w (disturbance.apply_windows). (N, 3) → (N, 3)."""
        from imugraph.calibration.alignment import undelay_magnetometer

        y = undelay_magnetometer(t, b_mag, self.mag_delay_s)
        for d in self.disturbances:
            inside = (t >= d["t_start"]) & (t <= d["t_end"])
            if d.get("modelled") and d.get("offset") is not None:
                y[inside] -= np.asarray(d["offset"], float)
                for a, b in d.get("left_out") or ():
                    y[(t >= a) & (t <= b)] = np.nan
            else:
                y[inside] = np.nan
        return y

    def corrected_gyro(self, b_gyr: np.ndarray) -> np.ndarray:
        """(I + E)·b_gyr, (N, 3) → (N, 3): the gyro with its scale/misalignment removed (not its bias), as
        calibration.ml preintegrated it (gyro_map.GyroMapState.corrected); b_gyr itself when E = 0."""
        from imugraph.calibration.gyro_map import corrected_rate

        b_gyr = np.asarray(b_gyr, float)
        return corrected_rate(b_gyr, self.gyro_map) if np.any(self.gyro_map) else b_gyr

    def to_dict(self) -> dict:
        def arr(x):
            return np.asarray(x, float).tolist()
        return {
            "D": arr(self.D), "o": arr(self.o), "dip_deg": float(self.dip_deg),
            "gyro_bias": arr(self.gyro_bias),
            "noise": {k: arr(v) for k, v in self.noise.items()},
            "std": {k: arr(v) for k, v in self.std.items()},
            "coverage": self.coverage, "converged": bool(self.converged),
            "iterations": int(self.iterations), "mag_delay_s": float(self.mag_delay_s),
            "disturbances": [dict(d) for d in self.disturbances],
            "gyro_map": arr(self.gyro_map), "acc_lead_samples": float(self.acc_lead_samples),
            "velocity_sigma": _opt_float(self.velocity_sigma), "velocity_tau": _opt_float(self.velocity_tau),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Calibration":
        return cls(
            D=np.asarray(d["D"], float).reshape(3, 3), o=np.asarray(d["o"], float).reshape(3),
            dip_deg=float(d["dip_deg"]), gyro_bias=np.asarray(d.get("gyro_bias", [0, 0, 0]), float),
            noise={k: np.asarray(v, float) for k, v in d.get("noise", {}).items()},
            std={k: np.asarray(v, float) for k, v in d.get("std", {}).items()},
            coverage=d.get("coverage", {}), converged=bool(d.get("converged", False)),
            iterations=int(d.get("iterations", 0)), mag_delay_s=float(d.get("mag_delay_s", 0.0)),
            disturbances=_disturbances(d.get("disturbances")),
            gyro_map=_gyro_map(d.get("gyro_map")),
            acc_lead_samples=float(d.get("acc_lead_samples", 0.0)),
            velocity_sigma=_opt_float(d.get("velocity_sigma")), velocity_tau=_opt_float(d.get("velocity_tau")),
        )


def _opt_float(value) -> float | None:
    """An optional positive number of calibration.json (absent or null → None)."""
    if value is None:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{str(value)[:60]!r}, expected a positive number or null") from None
    if not (np.isfinite(x) and x > 0):
        raise ValueError(f"{x!r}, expected a positive number or null")
    return x


def _window_number(d: dict, i: int, key: str) -> float:
    """disturbances[i][key] as a finite float (s), else ValueError naming the field."""
    if key not in d:
        raise ValueError(f"disturbances[{i}].{key}: missing, expected a time in s (a finite number)")
    v = d[key]
    try:
        if isinstance(v, (bool, str)) or v is None:
            raise TypeError
        x = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"disturbances[{i}].{key}: {str(v)[:60]!r}, expected a time in s (a finite number)") from None
    if not np.isfinite(x):
        raise ValueError(f"disturbances[{i}].{key}: {x!r}, expected a time in s (a finite number)")
    return x


def _window(d: dict, i: int) -> dict:
    """One disturbance window checked (the fields Calibration.corrected reads): t_start ≤ t_end finite (s),
    offset null/absent or 3 finite numbers (raw magnetometer unit), modelled absent/null or a boolean."""
    t0, t1 = _window_number(d, i, "t_start"), _window_number(d, i, "t_end")
    if t0 > t1:
        raise ValueError(f"disturbances[{i}].t_end: {t1!r} < t_start {t0!r}, expected t_start ≤ t_end")
    out = {**d, "t_start": t0, "t_end": t1}
    off = d.get("offset")
    if off is not None:
        try:
            arr = np.asarray(off, float) if isinstance(off, list) else None
        except (TypeError, ValueError):
            arr = None
        if arr is None or arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"disturbances[{i}].offset: {str(off)[:60]!r}, expected 3 finite numbers "
                             "(the window's hard-iron shift) or null")
        out["offset"] = arr.tolist()
    if d.get("modelled") is not None and not isinstance(d["modelled"], bool):
        raise ValueError(f"disturbances[{i}].modelled: {str(d['modelled'])[:60]!r}, expected true or false")
    return out


def _disturbances(value) -> list:
    """The optional `disturbances` field of calibration.json: absent or null → []; each window needs finite
    t_start ≤ t_end (s), an offset of 3 finite numbers or null, a boolean `modelled` if any (`_window`); its
    optional `left_out` must be a list of [t_a, t_b] pairs of finite numbers with t_a ≤ t_b (s).
    Raises ValueError whose message starts with the field, e.g. "disturbances[0].t_end: missing, ..."."""
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(d, dict) for d in value):
        raise ValueError(f"disturbances: {str(value)[:60]!r}, expected a list of objects")
    out = []
    for i, d in enumerate(value):
        d = _window(d, i)
        runs = d.get("left_out")
        if runs is not None:
            try:
                arr = np.asarray(runs, float).reshape(-1, 2) if len(runs) else np.zeros((0, 2))
            except (TypeError, ValueError):
                raise ValueError(f"disturbances[{i}].left_out: {str(runs)[:60]!r}, expected a list of "
                                 "[t_start, t_end] pairs of numbers") from None
            if arr.shape[0] != len(runs) or not np.all(np.isfinite(arr)) or np.any(arr[:, 0] > arr[:, 1]):
                raise ValueError(f"disturbances[{i}].left_out: {str(runs)[:60]!r}, expected a list of "
                                 "[t_start, t_end] pairs of finite numbers with t_start ≤ t_end")
            d = {**d, "left_out": arr.tolist()}
        out.append(dict(d))
    return out


def _gyro_map(value) -> np.ndarray:
    """The optional `gyro_map` field of calibration.json: absent or null → zeros; else a finite 3×3 array."""
    if value is None:
        return np.zeros((3, 3))
    try:
        E = np.asarray(value, float)
    except (TypeError, ValueError):
        raise ValueError(f"gyro_map: {str(value)[:60]!r}, expected a 3×3 array of numbers") from None
    if E.shape != (3, 3) or not np.all(np.isfinite(E)):
        raise ValueError(f"gyro_map: shape {E.shape} or non-finite entries, expected a finite 3×3 array")
    return E
