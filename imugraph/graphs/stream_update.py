"""One keyframe update of `StreamSmoother` (imugraph.graphs.stream): the solver's update with interval k's factors
and the read-back of the newest keyframe's estimate (a failed update keeps the prediction); split from stream.py."""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph import keys
from imugraph.graphs.cpp_velocity import imu_bias_key, pose_key
from imugraph.graphs.stream_field import field_key
from imugraph.graphs.stream_start import _quat


class KeyframeUpdateMixin:
    """`_isam` and `_update` of StreamSmoother (state lives in StreamSmoother.__init__)."""

    def _isam(self):
        """The iSAM2 instance holding the graph (the chain lag's inner one, or the solver itself)."""
        return self._solver.isam if self._chain else self._solver

    def _update(self, graph, values, stamps, k_new: int, seg: int, R_pred) -> None:
        try:
            chain = self._chain
            remove, force = self._realign_removals() if self.opt.gap_realign_s else ((), False)    # stream_realign
            if self.opt.lag_s is None or chain:
                if chain:      # only the keyframes leaving the window are read back (their smoothed output)
                    left = self._solver.update(graph, values, stamps, remove, force)
                    self._smoothed_kf.update(left or {})
                    if left:
                        self._forget_smoothed(k_new)
                else:
                    self._solver.update(graph, values, list(remove), None, None, None, force)
                isam = self._isam()
                est_pose = isam.calculateEstimatePose3(pose_key(k_new))
                est_v = isam.calculateEstimateVector(keys.vel(k_new))
                est_b = isam.calculateEstimateConstantBias(imu_bias_key(seg))
                est_d = isam.calculateEstimateVector(field_key(k_new)) if self._field else None
            else:
                ts = gtsam.FixedLagSmootherKeyTimestampMap()
                for key, s in stamps.items():
                    ts.insert((key, float(s)))
                self._solver.update(graph, values, ts)
                est = self._solver.calculateEstimate()
                poses = gtsam.utilities.extractPose3(est)
                first = k_new + 1 - poses.shape[0]
                for i, row in enumerate(poses):
                    self._smoothed_kf[first + i] = row[:9].reshape(3, 3).copy()
                self._forget_smoothed(first)
                est_pose, est_v = est.atPose3(pose_key(k_new)), est.atVector(keys.vel(k_new))
                est_b = est.atConstantBias(imu_bias_key(seg))
                est_d = est.atVector(field_key(k_new)) if self._field else None
        except (RuntimeError, IndexError, ValueError):
            # an ill-conditioned or failed update (counted): keep the prediction
            self.stats.failed_updates += 1
            if self.opt.lag_s is not None and not chain:     # smoothed output of a lag: the prediction where none
                self._smoothed_kf.setdefault(k_new - 1, self._nRk.matrix())
                self._smoothed_kf.setdefault(k_new, np.asarray(R_pred))
            self._nRk = gtsam.Rot3(R_pred)
            self._q_nk = tuple(_quat(self._nRk).tolist())      # Python floats: the per-sample product
            self._d = np.exp(-self.stride / self.rate / self.opt.field_tau) * self._d if self._field else self._d
            return
        self._nRk, self._p, self._v = est_pose.rotation(), est_pose.translation(), est_v
        self._b_gyr_est = est_b.gyroscope()
        if est_d is not None:
            self._d = np.asarray(est_d, float)
        self._b_now = tuple(float(v) for v in self._b_gyr_est)
        self._q_nk = tuple(_quat(self._nRk).tolist())      # Python floats: the per-sample product
