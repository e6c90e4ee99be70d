"""The outputs of `StreamSmoother` (imugraph.graphs.stream): the end of the stream (`finish`: the last interval, the
window's keyframes, the end-of-stream smoothing), the smoothed keyframes and samples, and the constant-memory
pruning of the fixed lag's smoothed keyframes."""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.errors import SessionError
from imugraph.factors.gyro import Preintegration
from imugraph.graphs.orientation_init import sample_orientations
from imugraph.graphs.stream_lag import window_rotations


class StreamOutputMixin:
    """Methods of StreamSmoother (state in StreamSmoother.__init__)."""

    def finish(self) -> None:
        """Close the last interval (its newest sample becomes the last keyframe, as `keyframe_layout`)."""
        if self._finished:
            return
        if len(self._buf) >= 2:
            last = self._buf.pop()
            self._close(last)
            self._buf = [last]
        if self._chain and self._k > 0:
            # the keyframes still in the window: their latest estimate (the others' is the one they left with)
            for k, R in window_rotations(self._solver).items():
                self._smoothed_kf.setdefault(k, R)
        if (self._online is not None or self._calstate) and self._k > 0:
            self._calibrate(self._kf_t[-1] - self._t0, flush=True)
        if self.opt.lag_s is None and self._k > 0:
            for _ in range(self.opt.final_updates):
                self._solver.update()
            # the end-of-stream smoothing: Levenberg–Marquardt on iSAM2's own factors from its estimate
            # (iSAM2 relinearises only past a threshold and can stop short of the batch optimum), with every
            # magnetometer factor re-issued with the final calibration when it was re-estimated online
            graph, values = self._final_graph(), self._solver.calculateEstimate()
            for extend in self._end_extensions:      # (graph, values) -> (graph, values), stream.py __init__
                graph, values = extend(graph, values)
            self._final = self._final_lm(graph, values)
            if self._calstate:           # calibration.json: what the end graph used (stream_online._end_calibration)
                self._end_calibration()
            self._learned_content()
        self._finished = True

    def _learned_changes(self) -> dict:
        """What the end graph estimated besides θ, as Calibration fields: the gyro map Ê (gyro_map_end, stream_gmap)
        and the velocity process σ̂_v, τ̂_v (velocity_end, stream_velocity); {} when neither."""
        changes = {}
        if self._gmap is not None and self._gmap.info.get("estimated"):
            changes["gyro_map"] = self._gmap.total(self._final)
        v = getattr(self, "velocity_end_result", None)
        if v is not None and "skipped" not in v:
            changes.update(velocity_sigma=float(v["sigma"]), velocity_tau=float(v["tau"]))
        return changes

    def _learned_content(self) -> None:
        """calibration.json carries `_learned_changes`, as the batch's calibration does, so that
        `smooth --calibration` applies them."""
        from dataclasses import replace

        changes = self._learned_changes()
        if changes:
            self.cal = replace(self.cal, **changes)

    def _forget_smoothed(self, keep_from: int) -> None:
        """Without keep_history (constant memory): drop the smoothed keyframes before `keep_from` that the
        online calibration no longer awaits (its oldest pending interval)."""
        if self.opt.keep_history:
            return
        lo = min(keep_from, self._pending[0][0]) if self._pending else keep_from
        for old in [key for key in self._smoothed_kf if key < lo]:
            del self._smoothed_kf[old]

    def keyframe_rotations(self) -> np.ndarray:
        """(K, 3, 3) smoothed nRb of every keyframe (after `finish`)."""
        self.finish()
        if self._k == 0:
            return (self._nRk.matrix() if self._nRk is not None else np.eye(3))[None]
        if self.opt.lag_s is None:
            return gtsam.utilities.extractPose3(self._final)[:, :9].reshape(-1, 3, 3)
        if not self.opt.keep_history:
            raise SessionError("stream", "keep_history", "False", "True to keep every keyframe of a fixed lag")
        return np.stack([self._smoothed_kf[k] for k in range(self._k + 1)])

    def smoothed(self) -> np.ndarray:
        """(N, 4) smoothed nRb w,x,y,z of every accepted sample in time order (needs keep_history)."""
        from imugraph.geometry import quat_to_rotmat

        if not self.opt.keep_history:
            raise SessionError("stream", "keep_history", "False", "True to reconstruct per-sample orientations")
        nRk = self.keyframe_rotations()
        if self._k == 0:
            return np.array([self._filtered()] * self.stats.accepted).reshape(-1, 4)
        # after finish() the buffer holds the last keyframe's own sample only
        lengths = np.array([len(q) for q in self._hist_kRb] + [1])
        kRb = quat_to_rotmat(np.vstack(self._hist_kRb + [np.array([[1.0, 0.0, 0.0, 0.0]])]))
        kf_samples = np.r_[0, np.cumsum(lengths[:-1])]
        sample_kf = np.repeat(np.arange(len(lengths)), lengths)
        pre = Preintegration(kf_samples, sample_kf, kRb, np.array(self._hist_dR), None, None, None, None,
                             gap_end=np.array(self._hist_gap, bool))
        return sample_orientations(nRk, pre)

    def times(self) -> np.ndarray:
        """Keyframe times, s (K,)."""
        return np.asarray(self._kf_t)

    def sample_times(self) -> np.ndarray:
        """Times of the accepted samples in time order, s: the rows of `smoothed()` (after `finish`)."""
        self.finish()
        return np.concatenate(self._hist_t + [np.array([r[0] for r in self._buf])])
