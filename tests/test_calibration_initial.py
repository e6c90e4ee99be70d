"""Initial estimates of the magnetometer calibration: rest, noise, ellipsoid, alignment, coverage.

Synthetic tests compare against the TRUE values used to generate the data; the BROAD tests compare
against facts measured independently (README: dip ≈ 69°, |m| ≈ 44 µT) and skip without the data.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.io

from imugraph.calibration.alignment import align_axes, estimate_mag_delay, gravity_up, undelay_magnetometer
from imugraph.calibration.coverage import check_coverage, rotation_coverage
from imugraph.calibration.ellipsoid import fit_ellipsoid
from imugraph.calibration.initial import initial_calibration
from imugraph.calibration.rest import detect_rest, noise_from_rest
from imugraph.config import broad_dir
from imugraph.errors import CalibrationError
from imugraph.geometry import expmap, integrate_gyro, quat_to_rotmat
from imugraph.io.session import Session

G = 9.81
S_TRUE = 50.0 * np.array([[1.10, 0.05, -0.03], [0.05, 0.95, 0.08], [-0.03, 0.08, 1.02]])
O_TRUE = np.array([12.0, -7.0, 30.0])


def _unit_sphere(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _simulate(gyr_true: np.ndarray, fs: float, D: np.ndarray, o: np.ndarray, dip_deg: float,
              rng: np.random.Generator, bias=np.zeros(3), sig=(0.003, 0.03, 0.4),
              n_lin=None) -> tuple[Session, np.ndarray]:
    """A session from body rates (N, 3): nRb by integration, acc = bRn(n_lin + g e_z), mag model."""
    n = gyr_true.shape[0]
    t = np.arange(n) / fs
    nRb = quat_to_rotmat(integrate_gyro(gyr_true, np.full(n, 1.0 / fs)))
    d = np.radians(dip_deg)
    n_mag = np.array([np.cos(d), 0.0, -np.sin(d)])
    n_acc = np.array([0.0, 0.0, G]) + (0.0 if n_lin is None else n_lin)
    acc = np.einsum("nji,nj->ni", nRb, np.broadcast_to(n_acc, (n, 3))) + rng.normal(0, sig[1], (n, 3))
    mag = np.einsum("ij,nkj,k->ni", D, nRb, n_mag) + o + rng.normal(0, sig[2], (n, 3))
    gyr = gyr_true + bias + rng.normal(0, sig[0], (n, 3))
    return Session(t=t, gyr=gyr, acc=acc, mag=mag, name="sim"), nRb


def _rich_rates(fs: float, T: float, rest_s: float = 3.0) -> np.ndarray:
    """Body rates turning about all three axes, with a rest at the start."""
    t = np.arange(int(T * fs)) / fs
    w = np.stack([1.2 * np.sin(2 * np.pi * 0.11 * t), 0.9 * np.sin(2 * np.pi * 0.07 * t + 1.0),
                  1.0 * np.sin(2 * np.pi * 0.05 * t + 2.0)], axis=1)
    w[t < rest_s] = 0.0
    return w


# ---------------------------------------------------------------- ellipsoid
def test_ellipsoid_recovers_true_symmetric_D_and_offset():
    rng = np.random.default_rng(1)
    y = _unit_sphere(rng, 4000) @ S_TRUE.T + O_TRUE + rng.normal(0, 0.5, (4000, 3))
    D0, o0 = fit_ellipsoid(y)
    np.testing.assert_allclose(D0, D0.T, atol=1e-9)
    assert np.max(np.abs(D0 - S_TRUE)) < 0.2          # 0.4 % of the 50-unit radius (noise 1 %)
    assert np.max(np.abs(o0 - O_TRUE)) < 0.2


def test_ellipsoid_of_misaligned_D_gives_its_symmetric_polar_factor():
    rng = np.random.default_rng(2)
    Q = expmap(np.radians(20.0) * np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5]))
    y = _unit_sphere(rng, 4000) @ (S_TRUE @ Q).T + O_TRUE + rng.normal(0, 0.5, (4000, 3))
    y[::7] = np.nan                                     # missing magnetometer rows are ignored
    D0, o0 = fit_ellipsoid(y)
    assert np.max(np.abs(D0 - S_TRUE)) < 0.2
    assert np.max(np.abs(o0 - O_TRUE)) < 0.2


def test_ellipsoid_ignores_a_disturbed_stretch():
    """A magnet attached for a third of the recording (a second sphere, shifted by more than its
    radius, as BROAD trial 32): the robust fit returns the undisturbed calibration."""
    rng = np.random.default_rng(12)
    y = _unit_sphere(rng, 6000) @ S_TRUE.T + O_TRUE + rng.normal(0, 0.5, (6000, 3))
    y[2000:4000] += [-8.0, -1.0, 65.0]
    D0, o0 = fit_ellipsoid(y)
    assert np.max(np.abs(D0 - S_TRUE)) < 0.3
    assert np.max(np.abs(o0 - O_TRUE)) < 0.3


@pytest.mark.parametrize("case", ["circle", "plane", "few", "line"])
def test_ellipsoid_refuses_degenerate_data(case):
    rng = np.random.default_rng(3)
    n = 3000
    if case == "circle":                                # rotation about one axis
        th = rng.uniform(0, 2 * np.pi, n)
        y = 40 * np.c_[np.cos(th), np.sin(th), np.full(n, 0.3)] + rng.normal(0, 0.3, (n, 3))
    elif case == "plane":
        y = np.c_[rng.uniform(-40, 40, (n, 2)), np.zeros(n)] + rng.normal(0, 0.3, (n, 3))
    elif case == "line":
        y = np.outer(rng.uniform(-40, 40, n), [1.0, 2.0, -1.0]) + rng.normal(0, 0.3, (n, 3))
    else:
        y = _unit_sphere(rng, 12) * 40
    with pytest.raises(CalibrationError, match="field 'mag'") as err:
        fit_ellipsoid(y)
    expected = "valid samples" if case == "few" else "too little rotation"
    assert expected in str(err.value)


# ---------------------------------------------------------------- alignment
def test_alignment_recovers_true_rotation_and_dip():
    rng = np.random.default_rng(4)
    n = 3000
    q = rng.normal(size=(n, 4))
    bRn = np.transpose(quat_to_rotmat(q / np.linalg.norm(q, axis=1, keepdims=True)), (0, 2, 1))
    dip = np.radians(69.0)
    m_b = bRn @ np.array([np.cos(dip), 0.0, -np.sin(dip)])
    u_b = bRn @ np.array([0.0, 0.0, 1.0])
    axis = np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)
    R_true = expmap(np.radians(8.0) * axis)
    m_tilde = m_b @ R_true + rng.normal(0, 0.01, (n, 3))    # m̃ = R_trueᵀ m_b
    R, dip_est, rms = align_axes(m_tilde, u_b + rng.normal(0, 0.01, (n, 3)))
    assert _angle_deg(R, R_true) < 0.5
    assert abs(np.degrees(dip_est) - 69.0) < 0.3
    assert rms < 0.03


def test_gravity_up_ignores_linear_acceleration():
    rng = np.random.default_rng(5)
    fs, T = 100.0, 60.0
    t = np.arange(int(fs * T)) / fs
    n_lin = 3.0 * np.stack([np.sin(2 * np.pi * 0.8 * t), np.cos(2 * np.pi * 0.5 * t), 0 * t], 1)
    s, nRb = _simulate(_rich_rates(fs, T, 0.0), fs, S_TRUE, O_TRUE, 60.0, rng, n_lin=n_lin)
    true_up = nRb[:, 2, :]
    up = gravity_up(s.gyr, s.acc, s.dt)
    err = np.degrees(np.arccos(np.clip(np.sum(up * true_up, 1), -1, 1)))
    raw = s.acc / np.linalg.norm(s.acc, axis=1, keepdims=True)
    err_raw = np.degrees(np.arccos(np.clip(np.sum(raw * true_up, 1), -1, 1)))
    assert np.median(err_raw) > 5.0                     # the raw direction is badly off...
    assert np.median(err) < 1.0                         # ...the gyro-frame average is not


def test_mag_delay_is_found():
    rng = np.random.default_rng(6)
    fs = 200.0
    s, _ = _simulate(_rich_rates(fs, 40.0, 0.0), fs, 50 * np.eye(3), np.zeros(3), 60.0, rng,
                     sig=(0.003, 0.03, 0.05))
    m = s.mag / 50.0
    lagged = np.vstack([np.repeat(m[:1], 2, axis=0), m[:-2]])   # 2 samples = 10 ms late
    assert abs(estimate_mag_delay(s.t, lagged, s.gyr) - 0.010) < 0.001
    assert abs(estimate_mag_delay(s.t, m, s.gyr)) < 0.001
    # undoing the lag restores the original samples (away from the held first rows)
    restored = undelay_magnetometer(s.t, lagged, 0.010)
    np.testing.assert_allclose(restored[5:-5], m[5:-5], atol=1e-12)
    assert np.all(np.isnan(restored[-2:]))                # no sample was read after the end


def test_undelay_keeps_missing_rows_missing():
    t = np.arange(10) * 0.01
    mag = np.column_stack([t, 2 * t, 3 * t])
    mag[1::2] = np.nan                                   # a magnetometer at half the rate
    out = undelay_magnetometer(t, mag, 0.021)             # 2 rows
    assert np.all(np.isnan(out[1::2])) and np.all(np.isfinite(out[0:-2:2]))
    np.testing.assert_allclose(out[0:-2:2, 0], t[2::2])
    assert np.isfinite(mag[0]).all() and np.isnan(mag[1]).all()     # the input is untouched


# ---------------------------------------------------------------- rest and noise
def _rest_session(rng: np.random.Generator, sig: np.ndarray) -> tuple[Session, np.ndarray]:
    fs, T = 100.0, 60.0
    t = np.arange(int(fs * T)) / fs
    rest = ((t >= 5) & (t < 15)) | ((t >= 35) & (t < 45))
    gyr = np.stack([np.sin(1.3 * t), np.cos(0.9 * t), np.sin(0.7 * t + 1)], 1) * 1.5
    acc = np.c_[3 * np.sin(2.1 * t), 2 * np.cos(1.7 * t), G + 2 * np.sin(3.1 * t)]
    mag = 40 * np.stack([np.cos(0.8 * t), np.sin(0.8 * t), np.sin(0.3 * t)], 1)
    seg2 = t >= 30                                      # per-segment offsets and a slow drift
    gyr[rest] = [0.01, -0.02, 0.005]
    acc[rest] = np.where(seg2[rest, None], [0.5, -0.3, 9.79], [0.1, 0.2, 9.80])
    mag[rest] = np.where(seg2[rest, None], [20.0, 3.0, -35.0], [-10.0, 15.0, -30.0])
    mag[rest] += 0.05 * (t[rest, None] - 10.0)
    gyr += rng.normal(0, 1, gyr.shape) * sig[0]
    acc += rng.normal(0, 1, acc.shape) * sig[1]
    mag += rng.normal(0, 1, mag.shape) * sig[2]
    mag[1::3] = np.nan                                  # multi-rate magnetometer
    return Session(t=t, gyr=gyr, acc=acc, mag=mag, name="rest"), rest


SIG = np.array([[0.002, 0.003, 0.004], [0.02, 0.03, 0.04], [0.3, 0.5, 0.7]])


def test_detect_rest_finds_the_rest_windows():
    s, rest_true = _rest_session(np.random.default_rng(7), SIG)
    rest = detect_rest(s, window_s=0.5)
    t = s.t
    inner = ((t > 5.3) & (t < 14.7)) | ((t > 35.3) & (t < 44.7))
    outer = ~(((t > 4.7) & (t < 15.3)) | ((t > 34.7) & (t < 45.3)))
    assert rest[inner].all()
    assert not rest[outer].any()


def test_constant_rate_turn_is_not_rest():
    fs = 100.0
    t = np.arange(3000) / fs
    s = Session(t=t, gyr=np.tile([0.0, 0.0, 0.5], (3000, 1)), acc=np.tile([0, 0, G], (3000, 1)),
                mag=np.c_[np.cos(0.5 * t), -np.sin(0.5 * t), np.zeros(3000)])
    assert not detect_rest(s).any()


def test_noise_from_rest_recovers_true_std_and_bias():
    s, _ = _rest_session(np.random.default_rng(8), SIG)
    nz = noise_from_rest(s, detect_rest(s))
    assert nz["method"] == "rest" and nz["mag_method"] == "rest"
    for k, ch in enumerate(("gyr", "acc", "mag")):
        np.testing.assert_allclose(nz[ch], SIG[k], rtol=0.10)
    np.testing.assert_allclose(nz["gyro_bias"], [0.01, -0.02, 0.005], atol=3e-4)


def test_noise_without_rest_falls_back_to_differences():
    s, _ = _rest_session(np.random.default_rng(9), SIG)
    nz = noise_from_rest(s, np.zeros(s.n, bool))
    assert nz["method"] == "differences" and nz["n_rest"] == 0
    np.testing.assert_allclose(nz["gyro_bias"], 0.0)
    for k, ch in enumerate(("gyr", "acc", "mag")):
        assert np.all(np.isfinite(nz[ch])) and np.all(nz[ch] > 0)
        np.testing.assert_allclose(nz[ch], SIG[k], rtol=0.15)


# ---------------------------------------------------------------- coverage and the whole chain
def test_rotation_about_one_axis_is_not_identifiable():
    rng = np.random.default_rng(10)
    fs = 100.0
    w = np.tile([0.0, 0.0, 0.6], (6000, 1))             # turntable: z up, turning about z
    s, _ = _simulate(w, fs, S_TRUE, O_TRUE, 60.0, rng)
    cov = rotation_coverage(s)
    assert not cov["identifiable"]
    assert cov["axis_share"] > 0.99
    assert any("one axis only (body z" in p for p in cov["problems"])
    with pytest.raises(CalibrationError, match="field 'mag'.*rotate the sensor about all three"):
        check_coverage(s)
    with pytest.raises(CalibrationError, match="field 'mag'"):
        initial_calibration(s)


def test_initial_calibration_recovers_simulated_truth():
    rng = np.random.default_rng(11)
    fs = 100.0
    R_true = expmap(np.radians(7.0) * np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74]))
    D_true = S_TRUE @ R_true.T                          # symmetric shape, then misalignment
    bias = np.array([0.01, -0.005, 0.008])
    s, _ = _simulate(_rich_rates(fs, 90.0), fs, D_true, O_TRUE, 60.0, rng, bias=bias)
    est = initial_calibration(s)
    assert est.coverage["identifiable"]
    assert np.max(np.abs(est.D - D_true)) < 0.01 * 50
    assert np.max(np.abs(est.o - O_TRUE)) < 0.005 * 50
    assert abs(np.degrees(est.dip_rad) - 60.0) < 0.5
    np.testing.assert_allclose(est.gyro_bias, bias, atol=1e-3)
    assert abs(est.mag_delay_s) < 0.002                 # no lag simulated
    np.testing.assert_allclose(est.noise["mag"], 0.4, rtol=0.15)
    cal = est.to_calibration()
    json.dumps(cal.to_dict())                           # the coverage record is JSON-ready
    np.testing.assert_allclose(cal.apply(s.mag[:50]), est.apply(s.mag[:50]))


# ---------------------------------------------------------------- BROAD (real data)
def _broad_session(name: str) -> Session:
    path = broad_dir() / f"{name}.mat"
    if not path.exists():
        pytest.skip(f"BROAD trial {path} not available")
    d = scipy.io.loadmat(path, variable_names=["imu_gyr", "imu_acc", "imu_mag", "sampling_rate"])
    fs = float(np.squeeze(d["sampling_rate"]))
    n = d["imu_gyr"].shape[0]
    return Session(t=np.arange(n) / fs, gyr=d["imu_gyr"], acc=d["imu_acc"], mag=d["imu_mag"],
                   source=str(path), name=name)


def _broad_trials() -> dict:
    path = broad_dir() / "trials.json"
    return json.loads(path.read_text())["trials"] if path.exists() else {}


@pytest.mark.parametrize("name", ["01_undisturbed_slow_rotation_A", "07_undisturbed_fast_rotation_B"])
def test_broad_initial_calibration_norm_and_dip(name):
    s = _broad_session(name)
    est = initial_calibration(s)
    norm = np.linalg.norm(est.apply(s.mag), axis=1)
    assert np.sqrt(np.mean((norm - 1.0) ** 2)) < 0.03
    assert abs(np.degrees(est.dip_rad) - 69.0) < 3.0
    assert np.degrees(np.linalg.norm(est.gyro_bias)) < 1.0          # README: ≈ 0.2 °/s
    assert 0.3 < np.mean(est.noise["mag"]) < 2.0                     # µT
    assert 0.005 < est.mag_delay_s < 0.015            # the magnetometer lags ≈ 3 samples


def test_broad_coverage_of_every_trial():
    """Every trial that rotates is identifiable; the "translation without rotation" trials
    (≤ 16–58° of tilt, groups 'translation' in trials.json) are not, and say why."""
    trials = _broad_trials()
    if not trials:
        pytest.skip("BROAD trials.json not available")
    checked = 0
    for name, info in trials.items():
        if not (broad_dir() / f"{name}.mat").exists():
            continue
        cov = rotation_coverage(_broad_session(name))
        if "translation" in info["groups"]:
            assert not cov["identifiable"], name
            assert any("small cap" in p for p in cov["problems"]), name
        else:
            assert cov["identifiable"], (name, cov["problems"])
        checked += 1
    assert checked > 0
