"""The in-memory single-IMU session every reader produces and every solver consumes.

Frames and units (DESIGN.md): gyroscope `b_gyr` rad/s, accelerometer `b_acc` m/s² (≈ +g up at rest),
magnetometer `b_mag` in any unit, all in the sensor (body) frame b. A magnetometer row of NaN means
"no new magnetometer sample at this instant" (multi-rate logs, samples held between updates).
`quat` is the optional truth nRb as w,x,y,z (NaN where unknown).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class Session:
    """One IMU recording.

    Attributes:
        t: (N,) sample times in s, strictly increasing.
        gyr: (N, 3) angular rate in rad/s, body frame.
        acc: (N, 3) specific force in m/s², body frame.
        mag: (N, 3) magnetic field, any unit; NaN rows where no magnetometer sample exists.
        quat: optional (N, 4) truth orientation nRb (w, x, y, z); NaN rows where unknown.
        movement: optional (N,) bool mask of samples to score (BROAD's `movement`).
        source: file the session was read from (for error messages).
        name: short name (file stem).
        meta: free-form extra information from the reader (units converted, samples dropped, ...).
    """

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    quat: Optional[np.ndarray] = None
    movement: Optional[np.ndarray] = None
    source: str = "<memory>"
    name: str = "session"
    meta: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def rate(self) -> float:
        """Nominal sampling rate in Hz (median of the time steps)."""
        return float(1.0 / np.median(np.diff(self.t)))

    @property
    def dt(self) -> np.ndarray:
        """(N,) time step from each sample to the next; the last repeats the median."""
        d = np.diff(self.t)
        return np.append(d, np.median(d))

    @property
    def mag_valid(self) -> np.ndarray:
        """(N,) bool: rows holding a real magnetometer sample."""
        return np.all(np.isfinite(self.mag), axis=1)

    def slice(self, start: int, stop: int) -> "Session":
        """A sub-session [start, stop) (for streaming, cross-validation and tests)."""
        s = slice(start, stop)
        return Session(
            t=self.t[s], gyr=self.gyr[s], acc=self.acc[s], mag=self.mag[s],
            quat=None if self.quat is None else self.quat[s],
            movement=None if self.movement is None else self.movement[s],
            source=self.source, name=self.name, meta=dict(self.meta),
        )

    def with_mag(self, mag: np.ndarray, name: Optional[str] = None) -> "Session":
        """A copy with another magnetometer signal (e.g. a distorted or calibrated one)."""
        return Session(self.t, self.gyr, self.acc, np.asarray(mag, float), self.quat, self.movement,
                       self.source, name or self.name, dict(self.meta))
