"""Sensor models of one 9-axis IMU (DESIGN.md; the measurement models of Kok & Schön, "Magnetometer
calibration using inertial sensors", IEEE Sensors J. 16(14), 2016; numbered here (S1)–(S3)):

    b_gyr,k = ω_k + δ_ω + e_ω,k                                  gyroscope        (S1)
    b_acc,k = bRn,k (n_acc,k − n_grav) + δ_a + e_a,k             accelerometer    (S2)
    b_mag,k = D · bRn,k · (F · n_mag) + o + e_m,k                magnetometer     (S3)

with n_grav = [0, 0, −g] (z up), n_mag = [cos δ, 0, −sin δ] (x along the horizontal field, dip δ),
F the field magnitude in the magnetometer's unit (1: unit sphere, ≈ 50: µT) and white Gaussian noise
e with per-axis standard deviations. In the paper's notation the magnetometer's D is F · D here
(`SensorParams.D_unit`), because the paper's n_mag has unit norm.

The gyroscope sample k is the rate that is constant over [t_k, t_{k+1}) (see `sim.motion`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imugraph.calibration.result import n_mag_from_dip
from imugraph.errors import SessionError
from imugraph.geometry import quat_to_rotmat
from imugraph.io.session import Session

_SOURCE = "<imugraph.sim.sensors>"


def _vec3(name: str, value) -> np.ndarray:
    """Validate a (3,) float vector (scalars are broadcast)."""
    arr = np.array(value, float)
    if arr.ndim == 0:
        arr = np.full(3, float(arr))
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise SessionError(_SOURCE, name, f"shape {arr.shape} values {arr.tolist()}", "3 finite numbers")
    return arr


@dataclass(frozen=True)
class SensorParams:
    """Parameters of the simulated IMU. The defaults are an ideal sensor (no bias, no noise, D = I).

    Attributes:
        gyro_bias: (3,) constant gyroscope bias δ_ω, rad/s.
        gyro_noise: (3,) gyroscope noise standard deviation per axis, rad/s.
        acc_noise: (3,) accelerometer noise standard deviation per axis, m/s².
        acc_bias: (3,) constant accelerometer bias, m/s².
        mag_D: (3, 3) magnetometer distortion applied to the field in the magnetometer's unit.
        mag_o: (3,) magnetometer offset (hard iron), magnetometer unit.
        dip_rad: dip δ of the field, rad (positive: field points down).
        field_norm: |field| F in the magnetometer's unit (1 for the unit sphere, ≈ 50 for µT).
        mag_noise: (3,) magnetometer noise standard deviation per axis, magnetometer unit.
        g: gravity magnitude, m/s².
        mag_every: a magnetometer sample every `mag_every`-th IMU sample (NaN rows between).

    Raises:
        SessionError: wrong shapes, non-finite or negative values, singular mag_D.
    """

    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_noise: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_noise: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    mag_D: np.ndarray = field(default_factory=lambda: np.eye(3))
    mag_o: np.ndarray = field(default_factory=lambda: np.zeros(3))
    dip_rad: float = float(np.deg2rad(60.0))
    field_norm: float = 1.0
    mag_noise: np.ndarray = field(default_factory=lambda: np.zeros(3))
    g: float = 9.81
    mag_every: int = 1

    def __post_init__(self) -> None:
        for name in ("gyro_bias", "gyro_noise", "acc_noise", "acc_bias", "mag_o", "mag_noise"):
            object.__setattr__(self, name, _vec3(name, getattr(self, name)))
        for name in ("gyro_noise", "acc_noise", "mag_noise"):
            if np.any(getattr(self, name) < 0):
                raise SessionError(_SOURCE, name, str(getattr(self, name).tolist()), "standard deviations ≥ 0")
        D = np.asarray(self.mag_D, float)
        if D.shape != (3, 3) or not np.all(np.isfinite(D)) or np.linalg.cond(D) > 1e8:
            raise SessionError(_SOURCE, "mag_D", f"shape {D.shape}", "an invertible finite 3×3 matrix")
        object.__setattr__(self, "mag_D", D)
        scalars = {"field_norm": self.field_norm, "g": self.g}
        for name, value in scalars.items():
            if not (np.isfinite(value) and value > 0):
                raise SessionError(_SOURCE, name, str(value), "a positive finite number")
        if int(self.mag_every) != self.mag_every or self.mag_every < 1:
            raise SessionError(_SOURCE, "mag_every", str(self.mag_every), "an integer ≥ 1")

    @property
    def D_unit(self) -> np.ndarray:
        """(3, 3) the paper's D, for a unit-norm n_mag: F · mag_D (what a calibration estimates)."""
        return self.field_norm * self.mag_D

    @property
    def n_mag(self) -> np.ndarray:
        """(3,) unit nav-frame field [cos δ, 0, −sin δ]."""
        return n_mag_from_dip(self.dip_rad)

    def to_dict(self) -> dict:
        """JSON-friendly copy (lists and floats) for `Session.meta`."""
        out = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            out[name] = np.asarray(value).tolist() if isinstance(value, np.ndarray) else value
        out["D_unit"] = self.D_unit.tolist()
        return out


def simulate_imu(
    t: np.ndarray,
    nRb: np.ndarray,
    b_omega: np.ndarray,
    n_acc: np.ndarray,
    params: SensorParams,
    rng: np.random.Generator,
    *,
    name: str = "simulated",
) -> Session:
    """Gyroscope, accelerometer and magnetometer readings along a motion, eqs. (S1)–(S3).

    Args:
        t: (N,) sample times, s, increasing.
        nRb: (N, 4) true orientation body → nav, w, x, y, z.
        b_omega: (N, 3) true body angular rate, rad/s.
        n_acc: (N, 3) true linear acceleration in the nav frame, m/s² (gravity excluded).
        params: sensor parameters.
        rng: random generator for the noise (always draws (N, 9) normals, even for zero noise).
        name: session name.

    Returns:
        Session with gyr (rad/s), acc (m/s²), mag (magnetometer unit, NaN rows between sub-rate
        samples), quat = nRb (the truth), movement = samples where ω ≠ 0 or n_acc ≠ 0, and
        meta {"simulated": True, "sensor_params": params.to_dict(), "acc_lead_samples": 0.0}.

    Raises:
        SessionError: inconsistent shapes or non-increasing times.
    """
    t, nRb, b_omega, n_acc = _check_motion(t, nRb, b_omega, n_acc)
    n = t.shape[0]
    e = rng.standard_normal((n, 9))
    bRn = np.swapaxes(quat_to_rotmat(nRb), -1, -2)

    gyr = b_omega + params.gyro_bias + e[:, 0:3] * params.gyro_noise                       # (S1)
    n_grav = np.array([0.0, 0.0, -params.g])
    acc = np.einsum("nij,nj->ni", bRn, n_acc - n_grav) + params.acc_bias \
        + e[:, 3:6] * params.acc_noise                                                      # (S2)
    b_field = bRn @ (params.field_norm * params.n_mag)
    mag = b_field @ params.mag_D.T + params.mag_o + e[:, 6:9] * params.mag_noise           # (S3)
    mag[np.arange(n) % int(params.mag_every) != 0] = np.nan

    moving = (np.linalg.norm(b_omega, axis=1) > 0) | (np.linalg.norm(n_acc, axis=1) > 0)
    # the rate is held over [t_k, t_{k+1}) (sim.motion): the strapdown forward rule is exact, so the
    # accelerometer rows need no re-timing (calibration.acc_timing.session_lead)
    meta = {"simulated": True, "sensor_params": params.to_dict(), "acc_lead_samples": 0.0}
    return Session(t=t, gyr=gyr, acc=acc, mag=mag, quat=nRb.copy(), movement=moving,
                   source="<simulation>", name=name, meta=meta)


def _check_motion(t, nRb, b_omega, n_acc) -> tuple[np.ndarray, ...]:
    """Validate and convert the motion arrays; returns float copies."""
    t = np.asarray(t, float)
    if t.ndim != 1 or t.shape[0] < 2 or np.any(np.diff(t) <= 0):
        raise SessionError(_SOURCE, "t", f"shape {t.shape}", "(N,) strictly increasing times, N ≥ 2")
    n = t.shape[0]
    arrays = {"nRb": (nRb, 4), "b_omega": (b_omega, 3), "n_acc": (n_acc, 3)}
    out = [t]
    for key, (value, width) in arrays.items():
        arr = np.array(value, float)
        if arr.shape != (n, width) or not np.all(np.isfinite(arr)):
            raise SessionError(_SOURCE, key, f"shape {arr.shape}", f"({n}, {width}) finite values")
        out.append(arr)
    return tuple(out)
