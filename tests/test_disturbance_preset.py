"""Windows handed to the calibration (Options.disturbance_preset) are used as given, not re-detected."""

import dataclasses

import numpy as np

from imugraph.calibration.ml import Options, calibrate
from imugraph.sim.scenario import distorted_session


def test_preset_window_is_used_and_its_offset_estimated():
    s, truth = distorted_session(2, duration_s=40.0, rate_hz=100.0)
    t = s.t - s.t[0]
    inside = (t >= 15.0) & (t <= 22.0)
    extra = 0.3 * np.linalg.norm(truth.D, 2) * np.array([1.0, -0.5, 0.2])   # raw-unit hard iron, 30 % |m|
    mag = s.mag.copy()
    mag[inside] += extra
    s2 = dataclasses.replace(s, mag=mag)
    a, b = s.t[0] + 15.0, s.t[0] + 22.0
    est = calibrate(s2, Options(disturbance_preset=((a, b),)), allow_weak=True)
    wins = est.info["disturbance_windows"]
    assert len(wins) == 1
    assert abs(wins[0]["t_start"] - a) < 0.02 and abs(wins[0]["t_end"] - b) < 0.02
    off = np.asarray(wins[0]["offset"])
    assert np.linalg.norm(off - extra) < 0.1 * np.linalg.norm(extra)
