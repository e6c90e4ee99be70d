"""The weak path of the calibration (D, o not identifiable: too little rotation) and its options:
Options.weak_mag_delay (the magnetometer lag estimated there too) and Options.weak_theta_fraction."""

import numpy as np
import pytest

from imugraph.calibration.initial import initial_calibration, weak_initial
from imugraph.calibration.ml import Options, _theta_prior_sigma, calibrate
from imugraph.errors import CalibrationError
from imugraph.evaluate import orientation_error
from imugraph.factors.theta import pack_theta
from imugraph.io.session import Session

RATE = 100.0
LAG_S = 0.02          # magnetometer lag behind the gyro: 2 samples
DIP = np.deg2rad(65.0)


def _heading(t: np.ndarray) -> np.ndarray:
    """Hand-like back-and-forth turning about the vertical (rad): two incommensurate sinusoids."""
    return 0.9 * np.sin(2 * np.pi * 0.4 * t) + 0.5 * np.sin(2 * np.pi * 0.23 * t + 1.0)


def lagged_one_axis_session(lag_s: float = LAG_S, duration_s: float = 40.0, seed: int = 0) -> Session:
    """Rotation about the vertical only (D, o not identifiable), the magnetometer sensing the field LAG_S
    before the gyro/accelerometer row it is stored with. Truth computed in closed form here, not by imugraph:
    nRb = Rz(ψ(t)); gyro ω_z,j = (ψ(t_{j+1}) − ψ(t_j))/Δt (exact under the forward strapdown rule);
    b_mag,j = 40 µT · Rz(ψ(t_j − lag))ᵀ n, n = [cos δ, 0, −sin δ]; b_acc = [0, 0, g]."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * RATE)
    t = np.arange(n) / RATE
    psi = _heading(t)
    gyr = np.zeros((n, 3))
    gyr[:-1, 2] = np.diff(psi) * RATE
    gyr[-1, 2] = gyr[-2, 2]
    gyr += rng.normal(0, 0.002, (n, 3))
    acc = np.tile([0.0, 0.0, 9.81], (n, 1)) + rng.normal(0, 0.03, (n, 3))
    p = _heading(t - lag_s)
    f = 40.0 * np.array([np.cos(DIP), 0.0, -np.sin(DIP)])
    mag = np.stack([np.cos(p) * f[0], -np.sin(p) * f[0], np.full(n, f[2])], 1) + rng.normal(0, 0.15, (n, 3))
    quat = np.stack([np.cos(psi / 2), np.zeros(n), np.zeros(n), np.sin(psi / 2)], 1)
    return Session(t, gyr, acc, mag, quat=quat, name="lagged_one_axis", source="lagged_one_axis.npz")


@pytest.fixture(scope="module")
def lagged():
    return lagged_one_axis_session()


def test_session_is_on_the_weak_path(lagged):
    with pytest.raises(CalibrationError):
        initial_calibration(lagged)


def test_weak_initial_estimates_the_lag_only_when_asked(lagged):
    assert weak_initial(lagged, "test").mag_delay_s == 0.0       # weak_initial's own default: not estimated
    est = weak_initial(lagged, "test", estimate_delay=True).mag_delay_s
    assert abs(est - LAG_S) < 0.002, est
    still = weak_initial(lagged_one_axis_session(lag_s=0.0), "test", estimate_delay=True).mag_delay_s
    assert abs(still) < 0.002, still


def test_calibrate_weak_mag_delay_option(lagged):
    """Options.weak_mag_delay (default on): the lag reaches the calibration record and the heading gets better
    than with the option off."""
    plain = calibrate(lagged, Options(max_outer=3, weak_mag_delay=False), allow_weak=True)
    fixed = calibrate(lagged, Options(max_outer=3), allow_weak=True)
    assert plain.calibration.mag_delay_s == 0.0
    assert abs(fixed.calibration.mag_delay_s - LAG_S) < 0.002
    assert fixed.calibration.coverage["identifiable"] is False
    e_plain = orientation_error(plain.quat, lagged.quat, None, RATE).rms_deg
    e_fixed = orientation_error(fixed.quat, lagged.quat, None, RATE).rms_deg
    assert e_fixed < 0.8 * e_plain, (e_fixed, e_plain)


def test_weak_theta_fraction_sets_the_prior():
    theta0 = pack_theta(44.0 * np.eye(3), np.zeros(3), 1.2)
    loose = _theta_prior_sigma(theta0, False, 1e-4)
    assert np.allclose(loose[:12], np.r_[np.full(9, 44.0), np.full(3, 88.0)])     # identifiable: unchanged
    tight = _theta_prior_sigma(theta0, True, 1e-4)
    assert np.allclose(tight[:9], 44.0e-4) and np.allclose(tight[9:12], 88.0e-4)
    assert np.isclose(tight[12], np.pi / 2)                                          # the dip stays free
    assert np.allclose(_theta_prior_sigma(theta0, True), _theta_prior_sigma(theta0, True, 0.05))


def test_broad_translation_trial_lag_matches_a_rotation_trial(data_dir):
    """BROAD 16 (fast translation, weak path): the lag from the field taken as calibrated agrees with the one
    the identifiable path measures on a rotation trial of the same sensor (01, ellipsoid-calibrated field)."""
    broad = data_dir / "broad"
    p16, p01 = broad / "16_undisturbed_fast_translation_B.mat", broad / "01_undisturbed_slow_rotation_A.mat"
    if not (p16.exists() and p01.exists()):
        pytest.skip("BROAD trials 01/16 absent")
    from imugraph.io.readers import load_session

    s16 = load_session(p16)
    with pytest.raises(CalibrationError):
        initial_calibration(s16)
    ref = initial_calibration(load_session(p01)).mag_delay_s
    lag = weak_initial(s16, "test", estimate_delay=True).mag_delay_s
    assert 0.005 < ref < 0.015
    assert abs(lag - ref) < 0.0015, (lag, ref)
