"""Options.window_trial_verdict on a recording whose rows outside the disturbance windows do not identify D
(BROAD 34's first 67 s: the magnet windows 44.6–67.5 s hold most of its rotation). The trial verdict left the
windows out for good and D drifted to singular values 76, 45, 4.7; the coverage check on the rows kept
(coverage.mag_spread_of_rows, rounds.identified_without_windows) now sends such windows to the σ_mag verdict."""

import numpy as np
import pytest

from imugraph.calibration.coverage import MAG_MIN_SPREAD, mag_spread_of_rows
from imugraph.calibration.disturbance import Window
from imugraph.calibration.rounds import identified_without_windows
from imugraph.geometry import expmap, rotmat_to_quat
from imugraph.io.session import Session

RATE = 100.0


def _circle_then_tumble(n_half: int = 3000) -> Session:
    """First half: yaw only about the vertical at 1 rad/s (the field's body-frame points lie on a circle: zero
    spread across its plane); second half: tumbling about all three axes (the points cover the sphere)."""
    t = np.arange(2 * n_half) / RATE
    gyr = np.zeros((2 * n_half, 3))                   # body rate, rad/s: nRb_k+1 = nRb_k Exp(ω_k dt)
    gyr[:n_half, 2] = 1.0
    tt = t[n_half:]
    gyr[n_half:] = np.c_[1.2 * np.sin(0.37 * tt), 1.0 * np.cos(0.29 * tt), 0.6 + 0 * tt]
    nRb = np.empty((len(t), 3, 3))
    nRb[0] = np.eye(3)
    steps = expmap(gyr / RATE)
    for k in range(1, len(t)):
        nRb[k] = nRb[k - 1] @ steps[k - 1]
    dip = np.deg2rad(60.0)
    n_mag = 50.0 * np.array([np.cos(dip), 0.0, -np.sin(dip)])
    rng = np.random.default_rng(3)
    mag = np.einsum("nji,j->ni", nRb, n_mag) + 0.3 * rng.standard_normal(gyr.shape)
    acc = np.einsum("nji,j->ni", nRb, np.array([0.0, 0.0, 9.81]))
    return Session(t=t, gyr=gyr, acc=acc, mag=mag, quat=rotmat_to_quat(nRb), source="<synthetic>",
                   name="circle_then_tumble", meta={})


def test_spread_of_rows_sees_a_circle_that_the_whole_recording_hides():
    s = _circle_then_tumble()
    half = np.arange(s.n) < s.n // 2
    assert mag_spread_of_rows(s, half) < 0.01                 # a circle: no spread across its plane
    assert mag_spread_of_rows(s, ~half) > 2 * MAG_MIN_SPREAD   # tumbling covers the sphere
    assert mag_spread_of_rows(s, np.ones(s.n, bool)) > MAG_MIN_SPREAD
    assert mag_spread_of_rows(s, np.zeros(s.n, bool)) == 0.0


def test_windows_holding_the_rotation_are_not_left_out_for_good():
    s = _circle_then_tumble()
    assert not identified_without_windows([Window(s.n // 2, s.n)], s)      # the rest is the circle
    assert identified_without_windows([Window(100, 600)], s)              # the tumbling half is kept
    assert identified_without_windows([], s)


def test_broad34_bootstrap_with_trial_verdict_identifies_D(data_file):
    """BROAD 34's first 19 286 samples (the stream bootstrap): with the option on D is a scaled rotation as with
    it off (singular values 51.0, 50.3, 48.8, benchmarks/b_window_short.py), not 76, 45, 4.7."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.io.readers import load_session

    p = data_file("broad/34_disturbed_attached_magnet_3cm.mat")
    sub = load_session(p).slice(0, 19286)
    est = calibrate(sub, Options(window_trial_verdict=True), allow_weak=True)
    sv = np.linalg.svd(est.calibration.D)[1]
    assert sv.max() / sv.min() < 1.15, sv                 # a sphere, not a flattened ellipsoid
    assert 40.0 < sv.min() and sv.max() < 60.0, sv        # ≈ the local field, ~50 µT
    assert all(w["modelled"] for w in est.calibration.disturbances), est.calibration.disturbances
