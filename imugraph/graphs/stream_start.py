"""Keyframe 0 and the gyro-bias segments of a stream (methods of `imugraph.graphs.stream.StreamSmoother`,
split from it to keep the module short; state in StreamSmoother.__init__)."""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph import keys
from imugraph.graphs.cpp_velocity import G_KEY, SIGMA_ACC_BIAS_RW, SIGMA_G, SIGMA_POS, gauss_markov_factors, imu_bias_key, pose_key
from imugraph.graphs.orientation_init import triad
from imugraph.graphs.stream_field import field_key, field_start_prior


def _quat(R: gtsam.Rot3) -> np.ndarray:
    """w, x, y, z of a Rot3 (w ≥ 0)."""
    q = R.toQuaternion()
    out = np.array([q.w(), q.x(), q.y(), q.z()])
    return -out if out[0] < 0 else out


class KeyframeStartMixin:
    """`_start` (keyframe 0) and `_new_segment` (a gyro-bias segment) of StreamSmoother."""

    def _start(self, graph, values, stamps, kRb, a, m_cal, ok) -> None:
        """Keyframe 0: TRIAD of interval 0's mean accelerometer and field, gauges, gravity."""
        n = len(ok)
        up = np.einsum("mij,mj->i", kRb[:n], a[:n])
        fld = np.einsum("mij,mj->i", kRb[:n][ok], m_cal[ok]) if ok.any() else np.cross(up, [0.0, 1.0, 0.0])
        self._nRk = gtsam.Rot3(triad(up[None], fld[None])[0])
        self._q_nk = tuple(_quat(self._nRk).tolist())
        values.insert(pose_key(0), gtsam.Pose3(self._nRk, np.zeros(3)))
        values.insert(keys.vel(0), np.zeros(3))
        graph.add(gauss_markov_factors(np.array([1.0]), self._sig_v, self._tau_v)[0])
        graph.add(gtsam.PoseTranslationPrior3D(pose_key(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, SIGMA_POS)))
        if self._estimate_g:
            n_grav = np.array([0.0, 0.0, -self._g])
            values.insert(G_KEY, n_grav)
            graph.add(gtsam.PriorFactorVector(G_KEY, n_grav, gtsam.noiseModel.Diagonal.Sigmas(SIGMA_G)))
        stamps[pose_key(0)] = stamps[keys.vel(0)] = 0.0
        if self._field:
            values.insert(field_key(0), np.zeros(3))
            graph.add(field_start_prior(field_key(0), self.opt.field_sigma))
            stamps[field_key(0)] = 0.0
        if self._pos_on:             # bounded position p_0 (stream_position eq. K3)
            self._position_start(graph, values, stamps)
        if self._calstate:           # θ = (D, o, δ) as a state, with its prior (stream_calstate)
            self._add_cal_state(graph, values, stamps)

    def _new_segment(self, graph, values, seg: int, elapsed: float) -> None:
        """A gyro-bias segment: prior about the calibration's bias, random walk from the previous one."""
        o = self.opt
        b_hat = gtsam.imuBias.ConstantBias(np.zeros(3), self._b_hat)
        prior = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, o.acc_bias_sigma), np.full(3, o.bias_prior_sigma)])
        values.insert(imu_bias_key(seg), gtsam.imuBias.ConstantBias(np.zeros(3), np.array(self._b_now)))
        graph.add(gtsam.PriorFactorConstantBias(imu_bias_key(seg), b_hat, prior))
        if self._seg >= 0:
            # the batch path spreads the walk over equal segments of the whole session; here: segment length
            rw = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, SIGMA_ACC_BIAS_RW),
                                                        np.full(3, max(o.bias_rw, 1e-9) * np.sqrt(o.bias_segment_s))])
            graph.add(gtsam.BetweenFactorConstantBias(imu_bias_key(self._seg), imu_bias_key(seg),
                                                      gtsam.imuBias.ConstantBias(), rw))
        self._seg = seg
