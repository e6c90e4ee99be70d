"""Ready-made simulated sessions with known truth: the embedded default of `imugraph demo`.

`distorted_session(seed)` simulates one IMU rotated randomly about all axes (rests at the start, the
end and twice in between) with a strongly distorted magnetometer, gyro bias and realistic noise, and
returns the truth a calibration should recover (Kok & Schön's D and o for a unit-norm n_mag).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imugraph.calibration.result import Calibration
from imugraph.io.session import Session
from imugraph.sim.distortion import random_distortion
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.sensors import SensorParams, simulate_imu


@dataclass(frozen=True)
class Truth:
    """What generated a simulated session.

    Attributes:
        D: (3, 3) the paper's D for a unit-norm n_mag (magnetometer unit): D⁻¹(b_mag − o) has unit norm.
        o: (3,) magnetometer offset, magnetometer unit.
        dip_rad: field dip δ, rad.
        gyro_bias: (3,) rad/s.
        noise: per-axis standard deviations {"gyr": (3,) rad/s, "acc": (3,) m/s², "mag": (3,) unit}.
        nRb: (N, 4) true orientation body → nav, w, x, y, z.
        field_norm: |field| in the magnetometer's unit.
    """

    D: np.ndarray
    o: np.ndarray
    dip_rad: float
    gyro_bias: np.ndarray
    noise: dict
    nRb: np.ndarray
    field_norm: float

    @property
    def dip_deg(self) -> float:
        return float(np.rad2deg(self.dip_rad))

    def to_calibration(self) -> Calibration:
        """The truth as a `Calibration` record (to compare with an estimate, or to apply)."""
        return Calibration(D=self.D.copy(), o=self.o.copy(), dip_deg=self.dip_deg,
                           gyro_bias=self.gyro_bias.copy(),
                           noise={k: np.asarray(v, float).copy() for k, v in self.noise.items()},
                           converged=True)


def distorted_session(
    seed: int,
    duration_s: float = 120.0,
    rate_hz: float = 100.0,
    *,
    field_norm: float = 50.0,
) -> tuple[Session, Truth]:
    """A simulated session with a distorted magnetometer, deterministic for a given seed.

    Draws (in this order, from `np.random.default_rng(seed)`): the motion (random rotations, 2 s rests
    at both ends, 2 pauses of 1.5 s, no translation); the distortion A, b as `random_distortion`
    (scale 0.75–1.3, skew ±6°, misalignment ≤ 6°, offsets ±1.2·field_norm); the dip δ ~ U[40°, 75°];
    the gyro bias (random sign × U[0.3, 0.7] °/s per axis); then the sensor noise. Noise levels:
    gyro 0.01 rad/s, accelerometer 0.05 m/s², magnetometer 1 % of the field, per axis.

    Args:
        seed: random seed.
        duration_s: length, s.
        rate_hz: sampling rate, Hz (all three sensors).
        field_norm: |field| in the magnetometer unit (50: µT-like numbers).

    Returns:
        (session, truth): session.quat holds the true nRb; truth.D = field_norm·A, truth.o = b.

    Raises:
        SessionError: a duration too short for the rests (see `random_rotation_motion`).
    """
    rng = np.random.default_rng(seed)
    t, nRb, b_omega, n_acc = random_rotation_motion(duration_s, rate_hz, rng, rest_s=2.0, pauses=2)
    A, b = random_distortion(rng, field_norm)
    dip_rad = float(np.deg2rad(rng.uniform(40.0, 75.0)))
    gyro_bias = np.deg2rad(rng.choice([-1.0, 1.0], 3) * rng.uniform(0.3, 0.7, 3))
    noise = {"gyr": np.full(3, 0.01), "acc": np.full(3, 0.05), "mag": np.full(3, 0.01 * field_norm)}
    params = SensorParams(gyro_bias=gyro_bias, gyro_noise=noise["gyr"], acc_noise=noise["acc"],
                          mag_D=A, mag_o=b, dip_rad=dip_rad, field_norm=field_norm,
                          mag_noise=noise["mag"])
    session = simulate_imu(t, nRb, b_omega, n_acc, params, rng, name=f"sim_distorted_{seed}")
    truth = Truth(D=params.D_unit, o=params.mag_o.copy(), dip_rad=dip_rad, gyro_bias=gyro_bias,
                  noise=noise, nRb=nRb, field_norm=float(field_norm))
    return session, truth


def magnet_comes_off_session(seed: int = 3, duration_s: float = 42.0, rate_hz: float = 50.0,
                             off_at_s: float = 14.0) -> tuple[Session, Calibration, Calibration]:
    """A distorted session whose sensor carries an attached magnet (an extra hard iron Δ of 0.3–0.35 of the field
    scale) until `off_at_s`, as BROAD 32's first minute does; the start calibration describes the magnet
    (o₀ = o + Δ, as a bootstrap over that stretch would). The stream's disturbance-window tests use it.

    Returns:
        (session, start calibration (o + Δ), true calibration (o)).
    """
    from dataclasses import replace

    session, truth = distorted_session(seed, duration_s, rate_hz)
    cal_true = truth.to_calibration()
    scale = float(np.cbrt(abs(np.linalg.det(cal_true.D))))
    delta = scale * np.array([0.3, -0.25, 0.35])
    mag = session.mag.copy()
    mag[session.t < session.t[0] + off_at_s] += delta
    return session.with_mag(mag), replace(cal_true, o=cal_true.o + delta), cal_true
