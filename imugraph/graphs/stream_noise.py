"""The magnetometer noise level σ_m re-estimated by the stream itself at the end of the stream (StreamOptions.noise_end).

The stream's magnetometer factors hold the 30-s bootstrap's σ_m (Calibration.noise["mag"]) to the end, while the batch
re-estimates it on the whole trial in every ML round (calibration/ml.py, `reestimate` until the σ move < noise_tol).
They differ notably where the bootstrap window is not the trial (BROAD 36 σ_m,z 1.25 vs 2.34; 32 2.02 vs 1.15; 07
0.82/0.80/0.78 vs 0.75/0.76/0.69), and σ_m sets the balance of magnetometer against gyro in every keyframe.
Here the batch's own estimator runs on the end-of-stream graph (full iSAM2 with history), as an end extension
(`StreamSmoother._end_extensions`, before the end Levenberg–Marquardt, stream_output.finish):

- solve the end graph (`_final_lm`); at its solution x, the batch's MeasurementBlock of the magnetometer channel over
  the stream's own per-sample rows (every closed interval's y_j and gyro rotation ΔR_j = kRb_j into keyframe k, kept
  with history), the batch's model and kernel (Huber 2, Options().mag_kernel):

      e_j = D ΔR_jᵀ R_kᵀ (n(δ) + d_k) + o − (y_j − Δo_w)     (factors.magnetometer; Δo_w of a modelled window)        (1)

  θ = (D, o, δ) and the windows those of the end graph's factors (stream_windows_end's end windows and θ when it
  rebuilt the graph; else the end θ and the causal windows' Δo_w); rows of a left-out window (or of a keyframe without
  a magnetometer factor) stay in with weight floor 0, as the batch's left-out rows (apply_windows; its default
  noise_skip_excluded=False): in the variance with their Huber weight, not in the information shares;
- `calibration.noise.reestimate` itself: per axis

      σ_m,axis² = Σ_j w_j e_j,axis² / (Σ_j w_j − p_m/3),   p_m = 3 Σ_k s_k + 13 + p_d                              (2)

  w_j the Huber weights at the current σ_m, s_k the magnetometer's share of keyframe k's rotation information (its
  Gauss–Newton trace against the gyro's: the interval factors' rotation rows on either side, read from the graph's
  ImuFactors, cov = (R_rotᵀ R_rot)⁻¹), 13 for θ, p_d = `field_dof` of the nav-field perturbation d_k (its hat
  matrix under the stream's σ_d, τ_d). As the batch's rounds, every `every`-th finite row (ml.py round_every =
  max(1, stride_batch // Options().round_min_samples), stride_batch = rate / Options().keyframe_hz);
- every magnetometer factor of the end graph rebuilt at the new σ_m (the same builders: stream_windows_end's
  `_graph`, else `_mag_factor(exact=True)`), re-solved; repeated until σ_m moves < Options().noise_tol
  (|Δ ln σ| on every axis, the batch's round tolerance) or `OUTER_MAX` solves.

What the batch does NOT re-estimate from residuals, neither does this: Σω and Σa (calibration.noise: "a chain of
between-factors can absorb its own residuals"; with the velocity chain the accelerometer is not a per-sample channel,
MeasurementBlock.use_acc False). The batch's gyr/acc σ come from its rest detector on the whole trial
(rest.noise_from_rest), which needs the raw gyro and accelerometer rows the stream does not keep: left open.

Place among the end extensions (stream_output._init_end_extensions): after windows_end (the rows' windows and θ are
the end graph's: the batch re-estimates the noise at its current windows, and its left-out rows enter (2)), before
velocity_end and gyro_map_end (their EM / E rounds then run on orientations solved at the end σ_m, as the batch's
rounds re-estimate σ_m, the velocity process and Ê together). The windows' verdicts do not use σ_m (robust scales
relative to the undisturbed rows), so the order windows → noise loses nothing.

Only the end-of-stream smoothed output and calibration.json (noise["mag"], `_learned_changes`) change; the filtered
output and the fixed lag are untouched. `StreamSmoother.noise_end_result`: σ_m start / end per axis, the path, solves,
p_m, n_eff, CPU. Measured on BROAD: docs/stream.md, "Session 19, helper Y".
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from imugraph.graphs.cpp_velocity import pose_key

OUTER_MAX = 4          # end-graph solves with a re-estimated σ_m (as stream_velocity.OUTER_MAX)
_NO_INFO_COV = 1e12    # rotation covariance of an interval without an ImuFactor rotation row (no information)


def mag_factor_indices(graph: gtsam.NonlinearFactorGraph) -> list:
    """Indices of the end graph's exact magnetometer factors: CustomFactors whose first key is a pose x_k and whose
    other keys are only its d_k (f_k), Δo_w keys (w) and θ (stream_calstate.pinned_mag_factor,
    stream_windows_end.theta_mag_factor; the criterion of EndWindows._base plus θ)."""
    from imugraph.graphs.stream_calstate import CAL_KEY

    out = []
    for i in range(graph.size()):
        if not graph.exists(i):
            continue
        f = graph.at(i)
        if not isinstance(f, gtsam.CustomFactor):
            continue
        ks = list(f.keys())
        s0 = gtsam.Symbol(ks[0])
        if s0.chr() != ord("x"):
            continue
        if all(key == CAL_KEY or gtsam.Symbol(key).chr() == ord("w")
               or (gtsam.Symbol(key).chr() == ord("f") and gtsam.Symbol(key).index() == s0.index()) for key in ks[1:]):
            out.append(i)
    return out


def rotation_covariances(graph: gtsam.NonlinearFactorGraph, K: int) -> np.ndarray:
    """(K−1, 3, 3) covariance of each interval's preintegrated rotation, from its ImuFactor's rotation rows (the
    non-robust Gaussian model of stream_kernels.split_noise_one: sqrt information R, cov = (R_rotᵀ R_rot)⁻¹); an interval
    without one gets no information (_NO_INFO_COV)."""
    cov = np.tile(np.eye(3) * _NO_INFO_COV, (max(K - 1, 0), 1, 1))
    imu = tuple(c for c in (getattr(gtsam, "ImuFactor", None), getattr(gtsam, "ImuFactorWithGravityVector", None)) if c)
    for i in range(graph.size()):
        if not graph.exists(i):
            continue
        f = graph.at(i)
        if not isinstance(f, imu):
            continue
        nm = f.noiseModel()
        if isinstance(nm, gtsam.noiseModel.Robust):       # the Huber velocity rows
            continue
        k = int(gtsam.Symbol(f.keys()[0]).index())
        R = np.asarray(nm.R())[:, :3]
        info = R.T @ R
        if k < K - 1 and np.trace(info) > 0:
            cov[k] = np.linalg.inv(info)
    return cov


class NoiseEnd:
    """The end extension (graph, values) -> (graph, values) of StreamOptions.noise_end (module docstring)."""

    def __init__(self, sm):
        from imugraph.calibration.options import Options

        o = Options()
        self.sm = sm
        self.tol = o.noise_tol
        self.kernel = o.mag_kernel
        self.every = max(1, int(round(sm.rate / o.keyframe_hz)) // o.round_min_samples)   # ml.py round_every

    # ---------------------------------------------------------------- the rows of eq. (1)
    def _windows(self):
        """stream_windows_end's extension when it rebuilt the end graph's magnetometer factors, else None."""
        from imugraph.graphs.stream_windows_end import end_windows

        return end_windows(self.sm)

    def _rows(self, x: gtsam.Values) -> tuple:
        """(kf (M,), ΔR_j (M, 3, 3), y_j − Δo_w (M, 3), weight floor (M,), θ (13,)) of every closed interval's row at
        the end graph's solution x (module docstring, eq. 1)."""
        from imugraph.geometry import quat_to_rotmat

        sm = self.sm
        kRb = quat_to_rotmat(np.concatenate(sm._hist_kRb))
        kf = np.repeat(np.arange(len(sm._hist_kRb)), [len(q) for q in sm._hist_kRb])
        ext = self._windows()
        if ext is not None:                       # the end windows (stream_windows_end eq. 1) and the end θ
            from imugraph.graphs.stream_windows_end import END_KEY0, LEFT_OUT

            y = np.array(np.concatenate(sm._hist_raw), float)
            lab = ext._labels()
            floor = (lab != LEFT_OUT).astype(float)
            for i, w in enumerate(ext.windows):
                if w.explained and w.offset is not None:
                    key = gtsam.symbol("w", END_KEY0 + i)
                    off = x.atVector(key) if x.exists(key) else np.asarray(w.offset, float)
                    y[lab == i] -= off
            return kf, kRb, y, floor, ext._solved_theta(x)
        y = np.array(np.concatenate(sm._hist_y), float)   # the start windows applied (Calibration.corrected)
        floor = np.zeros(len(y))
        starts = np.r_[0, np.cumsum([len(q) for q in sm._hist_kRb])]
        for k in sm._mag_index:                   # keyframes with a magnetometer factor; a causal window's Δo_w
            floor[starts[k]:starts[k + 1]] = 1.0
            okey = sm._mag_okey.get(k)
            if okey is not None and x.exists(okey):
                y[starts[k]:starts[k + 1]] -= x.atVector(okey)
        return kf, kRb, y, floor, sm._end_theta()

    def estimate(self, graph: gtsam.NonlinearFactorGraph, x: gtsam.Values, sigma: np.ndarray) -> tuple:
        """(σ̂_m (3,), info) by eq. (2) (calibration.noise.reestimate on the batch's MeasurementBlock) at x."""
        from imugraph.calibration.noise import field_dof, reestimate
        from imugraph.factors.field import field_key
        from imugraph.graphs.measurements import ChannelData, MeasurementBlock

        sm = self.sm
        K = sm._k + 1
        kf, kRb, y, floor, theta = self._rows(x)
        ok = np.all(np.isfinite(y), axis=1)
        keep = np.zeros(len(y), bool)
        keep[np.flatnonzero(ok)[::self.every]] = True          # rounds.thinned: every n-th finite row
        nRk = np.stack([x.atPose3(pose_key(k)).rotation().matrix() for k in range(K)])
        d = np.stack([x.atVector(field_key(k)) for k in range(K)]) if sm._field else None
        mag = ChannelData(kf=kf[keep], kRb=kRb[keep], values=y[keep], sigma=np.asarray(sigma, float),
                          kernel=self.kernel, weight_floor=floor[keep])
        block = MeasurementBlock(n_keyframes=K, acc=None, mag=mag, use_theta=True, use_acc=False,
                                 with_field=d is not None, field_offsets=d)
        dt_k = np.diff(np.asarray(sm._kf_t))[:K - 1]
        extra = None
        if d is not None:                         # d_k absorbs part of the field residuals (ml.py, field_dof)
            extra = {"mag": field_dof(block.field_information(nRk, theta), dt_k, sm.opt.field_sigma, sm.opt.field_tau)}
        cov = rotation_covariances(graph, K)
        new = reestimate(block, nRk, theta, cov, x, sm._sig_g, extra)
        return np.asarray(new["mag"], float), {"rows": int(keep.sum()), "field_dof": extra and extra["mag"],
                                               "tau": new.get("mag_tau")}

    # ---------------------------------------------------------------- the factors
    def _mag_factors(self, x: gtsam.Values) -> list:
        """The end graph's magnetometer factors at the current sm._sig_y, with the builders that made them."""
        from imugraph.geometry import quat_to_rotmat

        sm = self.sm
        ext = self._windows()
        if ext is not None:
            g = ext._graph(gtsam.NonlinearFactorGraph(), x)
            return [g.at(i) for i in range(g.size()) if isinstance(g.at(i), gtsam.CustomFactor)]
        out = [sm._mag_factor(k, quat_to_rotmat(sm._hist_kRb[k]), sm._hist_y[k], exact=True) for k in sm._mag_index]
        return [f for f in out if f is not None]

    def _rebuilt(self, graph, idx: list, x: gtsam.Values):
        """`graph` with the factors `idx` replaced by `_mag_factors` (None when their count differs)."""
        new = self._mag_factors(x)
        if len(new) != len(idx):
            return None
        drop = set(idx)
        g = gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            if graph.exists(i) and i not in drop:
                g.add(graph.at(i))
        for f in new:
            g.add(f)
        return g

    def __call__(self, graph, values):
        sm = self.sm
        start_cpu = time.thread_time()
        tau = sm.cal.coverage.get("noise_correlation", {}) if isinstance(sm.cal.coverage, dict) else {}
        res = {"sigma_start": np.asarray(sm._sig_y, float).tolist(), "sigma": np.asarray(sm._sig_y, float).tolist(),
               "outer": 0, "path": [], "every": self.every, "tau_factor": float(np.sqrt(tau.get("mag", 1.0)))}
        sm.noise_end_result = res
        if not (sm._calstate and sm.opt.keep_history and sm._mag_index and sm._hist_kRb):
            res["skipped"] = "no exact θ-state magnetometer factors in the end graph"
            return graph, values
        idx, n_new = mag_factor_indices(graph), len(self._mag_factors(values))
        if n_new != len(idx):                 # not the factors we can rebuild: leave the graph as it is
            res["skipped"] = f"{len(idx)} magnetometer factors found, {n_new} rebuilt"
            return graph, values
        x, sigma = values, np.asarray(sm._sig_y, float)
        for outer in range(OUTER_MAX):
            x = sm._final_lm(graph, x)
            new, info = self.estimate(graph, x, sigma)
            step = float(np.max(np.abs(np.log(new / sigma))))
            sm._sig_y = new                       # the factors' σ (stream.py: noise["mag"] × √τ_mag)
            graph = self._rebuilt(graph, mag_factor_indices(graph), x)
            sigma = new
            res["path"].append(new.tolist())
            res.update(outer=outer + 1, step=step, **info)
            if step < self.tol:
                break
        res.update(sigma=sigma.tolist(), cpu_s=time.thread_time() - start_cpu)
        return graph, x

    def noise(self) -> dict | None:
        """calibration.json's noise with the end σ_m (÷ √τ_mag: the stream reads noise["mag"] × √τ_mag), or None when
        the extension did not run."""
        res = getattr(self.sm, "noise_end_result", None)
        if res is None or "skipped" in res or not res["path"]:
            return None
        out = dict(self.sm.cal.noise)
        out["mag"] = np.asarray(res["sigma"], float) / res["tau_factor"]
        return out
