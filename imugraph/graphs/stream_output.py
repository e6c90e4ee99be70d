"""The outputs of `StreamSmoother` (imugraph.graphs.stream): the end of the stream (`finish`: the last interval, the
window's keyframes, the end-of-stream smoothing: its graph, extensions, Levenberg–Marquardt and calibration.json),
the filtered orientation, the smoothed keyframes and samples, and the constant-memory pruning of the fixed lag's
smoothed keyframes."""

from __future__ import annotations

import math
from dataclasses import replace

import gtsam
import numpy as np

from imugraph import keys
from imugraph.errors import SessionError
from imugraph.factors.gyro import Preintegration
from imugraph.graphs.cpp_velocity import pose_key
from imugraph.graphs.orientation_init import sample_orientations, triad
from imugraph.graphs.stream_field import field_key
from imugraph.graphs.stream_interval import NAN3 as _NAN3, qmul
from imugraph.graphs.stream_lag import window_rotations
from imugraph.graphs.stream_start import _quat


class StreamOutputMixin:
    """Methods of StreamSmoother (state in StreamSmoother.__init__)."""

    def _init_end_extensions(self) -> None:
        """The end-of-stream model extensions, each (graph, values) -> (graph, values), applied in order to the end
        graph before its Levenberg–Marquardt (`finish`); empty by default."""
        options = self.opt
        self._end_extensions: list = []
        if options.windows_end and options.lag_s is None:     # the end graph's windows from the whole stream
            from imugraph.graphs.stream_windows_end import attach
            attach(self)
        if options.noise_end and options.lag_s is None and options.keep_history:   # σ_m re-estimated (stream_noise)
            from imugraph.graphs.stream_noise import NoiseEnd
            self._noise_end = NoiseEnd(self)
            self._end_extensions.append(self._noise_end)
        if options.velocity_end != "off" and options.lag_s is None:   # σ_v, τ_v by EM on the end graph (stream_velocity)
            from imugraph.graphs.stream_velocity import VelocityEnd
            self._end_extensions.append(VelocityEnd(self, options.velocity_end))
        self._gmap = None                    # gyro_map_end: E estimated by the end graph (stream_gmap)
        if options.gyro_map_end and options.lag_s is None and options.keep_history:
            from imugraph.graphs.stream_gmap import EndGyroMap
            self._gmap = EndGyroMap(self)
            self._end_extensions.append(self._gmap.extend)
        if options.mag_delay_end and options.lag_s is None and options.keep_history:
            from imugraph.graphs.stream_delay_end import attach as attach_delay   # the lag re-estimated: FIRST
            attach_delay(self)

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
            for extend in self._end_extensions:      # (graph, values) -> (graph, values), _init_end_extensions
                graph, values = extend(graph, values)
            self._final = self._final_lm(graph, values)
            if self._calstate:           # calibration.json: what the end graph used (_end_calibration)
                self._end_calibration()
            self._learned_content()
        self._finished = True

    def _learned_changes(self) -> dict:
        """What the end graph estimated besides θ, as Calibration fields: the gyro map Ê (gyro_map_end, stream_gmap),
        the velocity process σ̂_v, τ̂_v (velocity_end, stream_velocity), σ̂_m (noise_end, stream_noise) and the lag τ̂
        when the end graph re-paired the rows with it (mag_delay_end, stream_delay_end); {} when none."""
        changes = {}
        if self._gmap is not None and self._gmap.info.get("estimated"):
            changes["gyro_map"] = self._gmap.total(self._final)
        v = getattr(self, "velocity_end_result", None)
        if v is not None and "skipped" not in v:
            changes.update(velocity_sigma=float(v["sigma"]), velocity_tau=float(v["tau"]))
        noise = self._noise_end.noise() if getattr(self, "_noise_end", None) is not None else None
        if noise is not None:                # noise_end: the end graph's σ_m (stream_noise)
            changes["noise"] = noise
        delay = getattr(self, "_delay_end", None)
        if delay is not None and delay.tau_s is not None:   # mag_delay_end: the lag the end graph paired rows with
            changes["mag_delay_s"] = float(delay.tau_s)
        return changes

    def _learned_content(self) -> None:
        """calibration.json carries `_learned_changes`, as the batch's calibration does, so that
        `smooth --calibration` applies them."""
        changes = self._learned_changes()
        if changes:
            self.cal = replace(self.cal, **changes)

    def _end_calibration(self) -> None:
        """After the end-of-stream smoothing: `self.cal` (calibration.json) becomes what the end graph used — the normal
        state's streamed θ (calib_final_theta) as D, o, dip and each detector window's final Δo_w as a modelled
        `disturbances` entry (the batch's format, calibration.result), one per run of consecutive keyframes whose
        factor carried it: y_j − Δo_w for j in the run (stream_offsets eq. 1; Calibration.corrected), so that
        `smooth --calibration` sees the field the end graph saw (options.calib_json_end_graph). Without windows and a
        majority swap: unchanged.
        The majority swap's hard iron stays in calibration_history.json's last row (normal_window).
        With windows_end (when it rebuilt the end graph): the end θ and the END windows instead (std: the streamed θ's)."""
        opt = self.opt
        if not (self._calstate and opt.calib_json_end_graph and opt.calib_final_theta and self._theta_end is not None
                and self._final is not None and self._mag_index and self._end_cal is not None):
            return
        if opt.windows_end:                         # the end windows and end θ (stream_windows_end.end_calibration)
            from imugraph.graphs.stream_windows_end import end_calibration
            cal = end_calibration(self, self._end_cal)
            if cal is not None:
                self.cal = cal
                return
        added = []
        for okey, k0, k1 in self._okey_runs():
            t = np.concatenate(self._hist_t[k0:k1 + 1])
            added.append({"t_start": float(t.min()), "t_end": float(t.max()),
                          "offset": np.asarray(self._final.atVector(okey), float).tolist(), "modelled": True,
                          "left_out": [], "window": int(gtsam.Symbol(okey).index()), "source": "stream"})
        self.cal = replace(self._end_cal, disturbances=list(self.cal.disturbances) + added)

    def _okey_runs(self) -> list:
        """[Δo_w key, first, last keyframe] per run of consecutive keyframes whose factor carried the same Δo_w key."""
        rows = []
        for k in sorted(self._mag_okey):
            okey = self._mag_okey[k]
            if rows and rows[-1][0] == okey and rows[-1][2] == k - 1:
                rows[-1][2] = k
            else:
                rows.append([okey, k, k])
        return rows

    def _final_graph(self) -> gtsam.NonlinearFactorGraph:
        """iSAM2's factors; with history, the magnetometer factors rebuilt exact: with the final calibration
        (online refit), or on (pose_k, d_k, Δo_w) when θ is a graph state (calib_states): at the streamed θ (the normal
        state's last estimate, calib_final_theta, the default since session 17) or at the pinned θ₀."""
        factors = self._solver.getFactorsUnsafe()
        # θ pinned (calib_states): the factors were linearised once when their interval closed (at the filtered
        # pose, d_k and θ_lin); re-issued exact at θ₀ (stream_calstate.pinned_mag_factor) — BROAD, 17 trials:
        # smoothed vs smooth_fixed of the same model 0.148° → 0.035° mean (BROAD 17, docs/stream.md "One model, two solvers")
        if (self._online is None and not self._calstate) or not self.opt.keep_history or not self._mag_index:
            return factors
        return self._exact_mag_graph(factors)

    def _exact_mag_graph(self, factors: gtsam.NonlinearFactorGraph) -> gtsam.NonlinearFactorGraph:
        """`factors` (iSAM2's) with every indexed keyframe's magnetometer factor replaced by one built exact from the
        history's rows (`_hist_y`, as they are paired now: stream_delay_end re-pairs them)."""
        from imugraph.geometry import quat_to_rotmat

        old = set(self._mag_index.values())
        graph = gtsam.NonlinearFactorGraph()
        for i in range(factors.size()):
            if i not in old and factors.exists(i):
                graph.add(factors.at(i))
        for k in self._mag_index:
            graph.add(self._mag_factor(k, quat_to_rotmat(self._hist_kRb[k]), self._hist_y[k], exact=True))
        return graph

    def _final_lm(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.Values:
        """The end-of-stream Levenberg–Marquardt (iSAM2). With the field perturbation the graph holds Python
        CustomFactors, which gtsam's C++ optimizer would call with a copy of every Values (O(K²),
        GTSAM_NOTES.md): then the Python-driven loop of imugraph.graphs.solver, keyframes in time order."""
        if not self._field and not (self._calstate and self.opt.keep_history and self._mag_index):   # no CustomFactor
            return gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
        from imugraph.graphs.gyro_map_block import beta_key
        from imugraph.graphs.solver import chain_ordering, optimize

        present = set(values.keys())
        order = [key for k in range(self._k + 1) for key in (pose_key(k), keys.vel(k), field_key(k), beta_key(k))
                 if key in present]        # stream_gmap's β_k (gyro_map_end), eliminated in the chain
        in_order = set(order)
        rest = [key for key in values.keys() if key not in in_order]
        return optimize(graph, [], values, chain_ordering(order, rest))[0]

    def _filtered(self) -> np.ndarray:
        return np.array(self._filtered_q())

    def _filtered_q(self) -> tuple:
        if self._q_nk is None:
            if not self._buf:
                return _NAN3 + (math.nan,)
            a, m = np.array(self._buf[0][4:7]), np.array(self._buf[0][7:10])
            m = self.cal.apply(m[None])[0] if np.all(np.isfinite(m)) else np.cross(a, [0.0, 1.0, 0.0])
            return tuple(_quat(gtsam.Rot3(triad(a[None], m[None])[0]).compose(gtsam.Rot3.Quaternion(*self._q_open))).tolist())
        q = qmul(self._q_nk, self._q_open)
        return q if q[0] >= 0 else (-q[0], -q[1], -q[2], -q[3])

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
