"""StreamOptions.noise_end (imugraph.graphs.stream_noise): the end graph re-estimates the magnetometer noise σ_m with
the batch's estimator (calibration.noise.reestimate), rebuilds its magnetometer factors and re-solves."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from imugraph.calibration.result import Calibration
from imugraph.graphs.stream_kernels import split_noise_one
from imugraph.graphs.stream_noise import OUTER_MAX, NoiseEnd, mag_factor_indices, rotation_covariances
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.sensors import SensorParams, simulate_imu

from stream_runs import stream_isolated as _stream, truth_rms as _truth_rms

SIGMA_M = 0.5            # the simulated magnetometer noise per axis (field 50)


def _session(seed: int = 0, rate: float = 50.0, duration: float = 60.0):
    """Random rotations without translation (sim.motion), white sensor noise; the true calibration."""
    rng = np.random.default_rng(seed)
    t, nRb, b_omega, _ = random_rotation_motion(duration, rate, rng, rest_s=2.0)
    noise = {"gyr": np.full(3, 0.01), "acc": np.full(3, 0.05), "mag": np.full(3, SIGMA_M)}
    p = SensorParams(gyro_bias=np.deg2rad([0.4, -0.5, 0.3]), gyro_noise=noise["gyr"], acc_noise=noise["acc"],
                     dip_rad=np.deg2rad(60.0), field_norm=50.0, mag_noise=noise["mag"])
    s = simulate_imu(t, nRb, b_omega, np.zeros((len(t), 3)), p, rng, name="noise_end")
    cal = Calibration(D=50.0 * np.eye(3), o=np.zeros(3), dip_deg=60.0, gyro_bias=p.gyro_bias.copy(), noise=noise,
                      converged=True)
    return s, cal


def _wrong(cal: Calibration, factor: float) -> Calibration:
    return replace(cal, noise={**cal.noise, "mag": cal.noise["mag"] * factor})


@pytest.fixture(scope="module")
def runs():
    """The start σ_m twice the simulated one: the option off and on (end windows off: the _mag_index path)."""
    s, cal = _session()
    start = _wrong(cal, 2.0)
    return s, _stream(s, start), _stream(s, start, noise_end=True)


def test_recovers_the_true_sigma_from_twice(runs):
    """σ̂_m within 10 % of the simulated 0.5 on every axis from a start of 1.0; within OUTER_MAX solves; calibration.json
    carries it, gyr and acc unchanged."""
    s, (off, _), (on, _) = runs
    r = on.noise_end_result
    assert np.allclose(r["sigma_start"], 2 * SIGMA_M)
    assert np.all(np.abs(np.asarray(r["sigma"]) / SIGMA_M - 1) < 0.10), r
    assert 1 <= r["outer"] <= OUTER_MAX and r["step"] < 0.02, r
    assert np.allclose(on.cal.noise["mag"], r["sigma"])
    assert np.array_equal(on.cal.noise["gyr"], off.cal.noise["gyr"]) and np.array_equal(on.cal.noise["acc"],
                                                                                         off.cal.noise["acc"])
    assert np.allclose(off.cal.noise["mag"], 2 * SIGMA_M)                # off: the start's


def test_recovers_the_true_sigma_from_half():
    """The same from a start of 0.25 (half), through the end windows' factors (windows_end="theta", the default)."""
    s, cal = _session(1)
    on, _ = _stream(s, _wrong(cal, 0.5), noise_end=True, windows_end="theta")
    r = on.noise_end_result
    assert "skipped" not in r
    assert np.all(np.abs(np.asarray(r["sigma"]) / SIGMA_M - 1) < 0.10), r


def test_filtered_output_unchanged_smoothed_not_worse(runs):
    """The filtered output is identical with the option; the smoothed one no worse against the truth (0.02°)."""
    s, (off, q_off), (on, q_on) = runs
    assert np.array_equal(q_off, q_on)
    assert _truth_rms(on.smoothed(), s) <= _truth_rms(off.smoothed(), s) + 0.02


def test_factors_replaced_not_duplicated(runs):
    """The end graph's magnetometer factors are found (one per keyframe with a field), and rebuilt at the start σ_m they
    reproduce the graph's error at the end solution: replaced, not added."""
    s, (off, _), _ = runs
    graph = off._final_graph()
    idx = mag_factor_indices(graph)
    assert len(idx) == len(off._mag_index) > 0
    ext = NoiseEnd(off)
    rebuilt = ext._rebuilt(graph, idx, off._final)
    assert rebuilt is not None and rebuilt.size() == graph.size()
    assert np.isclose(rebuilt.error(off._final), graph.error(off._final), rtol=1e-12)


def test_rotation_covariances_read_back_from_the_factor():
    """An ImuFactor whose rotation rows carry split_noise_one(cov) gives back cov; its Huber velocity rows are not read;
    an interval without a factor has no information."""
    cov = np.array([[2.0, 0.3, 0.1], [0.3, 1.5, -0.2], [0.1, -0.2, 1.0]]) * 1e-6
    pim = gtsam.PreintegratedImuMeasurements(gtsam.PreintegrationParams.MakeSharedU(9.81))
    pim.integrateMeasurement(np.zeros(3), np.array([0.0, 0.0, 9.81]), 0.1)
    x = lambda k: gtsam.symbol("x", k)                              # noqa: E731
    v = lambda k: gtsam.symbol("v", k)                              # noqa: E731
    f = gtsam.ImuFactor(x(1), v(1), x(2), v(2), gtsam.symbol("b", 0), pim)
    rot, vel = split_noise_one(cov, 0.05, 2.0)
    g = gtsam.NonlinearFactorGraph()
    g.add(f.cloneWithNewNoiseModel(rot))
    g.add(f.cloneWithNewNoiseModel(vel))
    out = rotation_covariances(g, 4)
    assert np.allclose(out[1], cov, rtol=1e-9)
    assert out[0][0, 0] > 1e6 and out[2][0, 0] > 1e6


def test_right_start_stays():
    """From the true σ_m the estimate stays within 10 % (no drift of the dof correction) in one or two solves."""
    s, cal = _session(2, duration=40.0)
    on, _ = _stream(s, cal, noise_end=True)
    r = on.noise_end_result
    assert np.all(np.abs(np.asarray(r["sigma"]) / SIGMA_M - 1) < 0.10) and r["outer"] <= 2, r
