"""The gyro-map path of calibration.ml: the final (all-sample) solve runs on a graph without the rounds'
β_k / e keys (graphs.gyro_map_block.without_map_keys), and the settling gate falls back to the plain
model's rounds: continued from the E rounds' state with Ê = 0 ("warm", default: the plain optimum within
noise) or run from the kept starting state ("restart": the same result as a run without E)."""

from dataclasses import replace

import gtsam
import numpy as np

from imugraph import keys
from imugraph.graphs.gyro_map_block import E_KEY, beta_key, without_map_keys


def test_without_map_keys_drops_only_beta_and_e():
    v = gtsam.Values()
    for k in range(3):
        v.insert(keys.rot(k), gtsam.Rot3())
        v.insert(beta_key(k), np.full(3, k, float))
        v.insert(keys.bias(k), np.ones(3))
    assert without_map_keys(v) is v                      # nothing to drop: the same object
    v.insert(E_KEY, np.zeros(9))
    out = without_map_keys(v)
    assert out.size() == 6 and not out.exists(E_KEY)
    assert not any(out.exists(beta_key(k)) for k in range(3))
    assert all(out.exists(keys.rot(k)) and out.exists(keys.bias(k)) for k in range(3))
    assert v.size() == 10                                  # the input is unchanged


def test_gyro_map_final_solve_moves_and_fallback_equals_plain():
    """Simulation with a known gyro scale/misalignment: E settles, and the final solve on every field
    sample lowers its cost (before the fix it met an indeterminate system at every λ and returned its start).
    With one round allowed E cannot settle: the "restart" fallback's result equals the plain model's run."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.sim.scenario import distorted_session

    E_true = np.array([[0.005, 0.003, 0.0], [0.003, -0.004, -0.002], [0.0, -0.002, 0.006]])
    s, _ = distorted_session(1, 40.0, 100.0)
    s = replace(s, gyr=s.gyr @ np.linalg.inv(np.eye(3) + E_true).T)
    est = calibrate(s, Options(gyro_map=True, gyro_map_min_turns=0.0))
    assert est.info["gyro_map_gate"]["estimated"] is True
    cost0, cost1 = est.info["final_cost"]
    assert cost1 < cost0 and est.info["lm_iterations_final"] >= 1
    one = dict(max_outer=1, gyro_map_min_turns=0.0)
    fell = calibrate(s, Options(gyro_map=True, gyro_map_fallback="restart", **one))
    plain = calibrate(s, Options(gyro_map=False, **one))
    assert fell.info["gyro_map_gate"]["estimated"] is False and len(fell.info["gyro_map_gate"]["rounds"]) == 1
    np.testing.assert_array_equal(fell.quat, plain.quat)
    np.testing.assert_array_equal(fell.calibration.D, plain.calibration.D)
    assert fell.calibration.iterations == plain.calibration.iterations


def test_warm_fallback_reaches_the_plain_optimum():
    """Settling gate forced to fail (max contraction 0): the default "warm" fallback continues the plain
    rounds from the E rounds' state with Ê = 0. Its result is the plain model's ML estimate reached from a
    different start: equal to the from-scratch plain run within a small fraction of θ's std, and its
    orientations within a few millidegrees; "restart" is bit-identical to the plain run."""
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.factors.theta import pack_theta
    from imugraph.geometry import quat_conj, quat_mul
    from imugraph.sim.scenario import distorted_session

    E_true = np.array([[0.005, 0.003, 0.0], [0.003, -0.004, -0.002], [0.0, -0.002, 0.006]])
    s, _ = distorted_session(1, 40.0, 100.0)
    s = replace(s, gyr=s.gyr @ np.linalg.inv(np.eye(3) + E_true).T)
    forced = dict(gyro_map=True, gyro_map_min_turns=0.0, gyro_map_max_contraction=0.0)
    warm = calibrate(s, Options(gyro_map_fallback="warm", **forced))
    plain = calibrate(s, Options(gyro_map=False))
    gate = warm.info["gyro_map_gate"]
    assert gate["estimated"] is False and gate["fallback"] == "warm" and len(gate["rounds"]) == 2
    assert np.all(warm.calibration.gyro_map == 0.0)
    assert warm.calibration.converged and plain.calibration.converged

    def theta(c):
        return pack_theta(c.D, c.o, np.deg2rad(c.dip_deg))

    std = np.r_[plain.calibration.std["D"].ravel(), plain.calibration.std["o"],
                np.deg2rad(plain.calibration.std["dip_deg"])]
    assert np.max(np.abs(theta(warm.calibration) - theta(plain.calibration)) / std) < 0.05
    dq = quat_mul(quat_conj(plain.quat), warm.quat)
    angle = np.rad2deg(2 * np.arcsin(np.clip(np.linalg.norm(dq[:, 1:], axis=1), 0, 1)))
    assert angle.max() < 0.01
    restart = calibrate(s, Options(gyro_map_fallback="restart", **forced))
    np.testing.assert_array_equal(restart.quat, plain.quat)
    np.testing.assert_array_equal(restart.calibration.D, plain.calibration.D)
