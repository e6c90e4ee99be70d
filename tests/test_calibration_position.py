"""The bounded-position option (Options.position_sigma; graphs/velocity_block.py (P1))."""

import gtsam
import numpy as np

from imugraph import keys
from imugraph.calibration.ml import Options, calibrate
from imugraph.evaluate import orientation_error
from imugraph.graphs.velocity_block import POSITION_KIN_SIGMA, VelocityBlock, pos_key
from imugraph.sim.scenario import distorted_session


def test_position_terms_match_the_written_model():
    """graph.error of `position_graph` equals ½ Σ of the (P1) terms written out here by hand."""
    rng = np.random.default_rng(3)
    dt = np.array([0.2, 0.2, 0.35])
    K = len(dt) + 1
    sigma_p, tau_p = 0.8, 12.0
    vb = VelocityBlock(dv=np.zeros((K - 1, 3)), sigma_dv=np.ones(K - 1), dt_k=dt, g=9.81, position=(sigma_p, tau_p))
    v, p = rng.normal(0, 0.3, (K, 3)), rng.normal(0, 0.5, (K, 3))
    values = gtsam.Values()
    for k in range(K):
        values.insert(keys.vel(k), v[k])
        values.insert(pos_key(k), p[k])
    expected = np.sum((p[0] / sigma_p) ** 2)
    for k in range(K - 1):
        expected += np.sum(((p[k + 1] - p[k] - v[k] * dt[k]) / POSITION_KIN_SIGMA) ** 2)
        phi = np.exp(-dt[k] / tau_p)
        expected += np.sum(((p[k + 1] - phi * p[k]) / (sigma_p * np.sqrt(1 - phi**2))) ** 2)
    assert np.isclose(vb.position_graph().error(values), 0.5 * expected, rtol=1e-9)


def test_position_bound_keeps_a_resting_place_and_the_orientation():
    """A simulated session without translation: with the bound the smoothed velocities travel no farther than
    without it, and the orientation stays as good (within 0.02°)."""
    s, _ = distorted_session(21, duration_s=60, rate_hz=50)
    runs = {}
    for name, opt in (("off", Options()), ("on", Options(position_sigma=1.0))):
        est = calibrate(s, opt)
        dt = np.diff(s.t[est.info["keyframe_samples"]])
        travel = np.cumsum(est.info["velocity"][:-1] * dt[:, None], axis=0)
        runs[name] = (np.max(np.ptp(travel, axis=0)), orientation_error(est.quat, s.quat, None, s.rate).rms_deg)
    assert runs["on"][0] <= runs["off"][0] + 1e-3, runs
    assert runs["on"][1] <= runs["off"][1] + 0.02, runs
