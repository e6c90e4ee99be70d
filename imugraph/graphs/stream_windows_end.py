"""The end-of-stream graph's disturbance windows re-derived from the WHOLE stream with the batch's own detector and
verdict (`StreamOptions.windows_end`, off by default; issue 3, BROAD 32 / 34 / 36).

The stream decides its windows causally: the start calibration's own windows (fitted on the bootstrap, their offsets
fixed) and the detector's (stream_disturb, each with a free Δo_w, stream_offsets). The batch finds its windows on the
whole recording (calibration.disturbance.detect_windows on the norm of the calibrated field), fits each window's
hard-iron offset at the solve's orientations and keeps it modelled only when the offset explains the window on a
solve WITH it modelled (fit_offsets_on_trial), else leaves its samples out. At the end of a stream under full iSAM2
the whole trial is at hand (every interval's magnetometer rows, `_hist_raw`, and gyro rotations kRb are kept), so
the end graph can hold the batch's windows instead of the causal ones. Model (calibration.disturbance, eq.
"windowed hard iron", per sample j of keyframe interval k):

    y_j = D (R_k kRb_j)ᵀ (n(δ) + d_k) + o_n + Δo_w + e_j,   j ∈ w modelled;   j ∈ w unexplained: left out       (1)

with θ = (D, o, δ) the stream's end θ (calib_final_theta: the normal state's streamed θ; else θ₀) and o_n its hard
iron of the NORMAL state = the majority of the recording, as the batch: o + Δo of the stream's majority window when
its last record swapped (stream_offsets eq. 2; `_streamed_cal.o`), else θ's o. The windows are detected on
|D⁻¹(y − o_n)| − 1 over every raw sample (the start calibration's windows are NOT applied: they came from the
bootstrap alone). Each keyframe's magnetometer factor (stream_calstate.pinned_mag_factor, the same exact factor the
end graph holds) is split by the rows' labels: the normal rows one factor without offset, the rows of each modelled
window one factor on its Δo_w key (`END_KEY0 + i`, free with stream_offsets' weak prior), the left-out rows none.

Rounds (the batch's, calibration.rounds.fit_windows with window_trial_verdict): (a) at iSAM2's estimate (orientations
R_k, d_k) each window's Δo_w = median residual; put on trial when it removes most of the residual (TRIAL_GAIN), else
left out; (b) with any window on trial, one Levenberg–Marquardt solve (`_final_lm`) of the graph with them modelled,
then the verdict there: kept when its robust residual scale ≤ EXPLAINED × that of the undisturbed rows of the same
solve; (c) the graph with the verdicts goes to `finish`'s own end LM (from (b)'s solution). θ is held at θ_n.

windows_end="theta": θ = (D, o, δ) is also a variable of the end graph whenever a window is modelled (on trial in
(b), kept in (c)): every magnetometer factor on (pose_k, d_k, θ, Δo_w) (`theta_mag_factor`, stream_calstate eq. 2),
θ's pin replaced by the stream's weak prior Λ_w (calib_prior_rel) centred at θ_n. Why: the streamed θ never had the
window keyframes' information (stream_offsets: their factors carry no θ), while the batch's D and dip use every
modelled window's samples (their o absorbed by Δo_w). BROAD 34 (windows 44.5–100 s of 130 s; docs/stream.md
"Session 18, helper W"): the windows alone leave it 1.32° from the batch, with θ free 0.34°. Without a modelled
window θ stays held (36: left-out windows only; θ free there moved it 0.51 → 0.69° from the batch).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from imugraph.calibration.disturbance import (Window, detect_windows, field_residuals, fit_offsets_on_trial,
                                              robust_scale)
from imugraph.factors.field import field_key
from imugraph.factors.theta import pack_theta, unpack_theta
from imugraph.geometry import quat_to_rotmat
from imugraph.graphs.cpp_velocity import pose_key
from imugraph.graphs.stream_calstate import CAL_KEY, cal_mag_jacobians, pinned_mag_factor
from imugraph.graphs.stream_offsets import OFFSET_PRIOR_REL

__all__ = ["END_KEY0", "EndWindows", "attach", "end_calibration"]

END_KEY0 = 100000         # Δo_w keys of the end windows: offset-symbol indices from here (the causal ones count from 0)
NORMAL, LEFT_OUT = -1, -2  # row labels besides a window's index


def theta_mag_factor(pose_k: int, field_k: int | None, cal_key: int, offset_key: int | None, kRb: np.ndarray,
                     y: np.ndarray, sig_y: np.ndarray, huber_k: float | None):
    """Eq. (1) exact with θ a variable (windows_end="theta"): a CustomFactor on (pose_k, d_k — None: none —, θ, a
    window's Δo_w — None: none), e = D M_k R_kᵀ(n(δ) + d_k) + o + Δo_w − ȳ_k, Σ = diag(σ_y²)/n_k, Huber; error and
    Jacobians those of stream_calstate.cal_mag_jacobians (eq. 2), ∂e/∂Δo_w = I. None without a valid sample."""
    ok = np.all(np.isfinite(y), axis=1)
    n = int(ok.sum())
    if n == 0:
        return None
    M, y_avg = kRb[ok].sum(axis=0).T / n, y[ok].sum(axis=0) / n
    has_d, has_o = field_k is not None, offset_key is not None
    keys_ = [pose_k] + ([field_k] if has_d else []) + [cal_key] + ([offset_key] if has_o else [])

    def error(this, values, H):
        d = values.atVector(field_k) if has_d else np.zeros(3)
        e, J_pose, J_d, J_th = cal_mag_jacobians(values.atPose3(pose_k).rotation().matrix(), d,
                                                 values.atVector(cal_key), M, y_avg)
        if has_o:
            e = e + values.atVector(offset_key)
        if H is not None:
            blocks = [J_pose] + ([J_d] if has_d else []) + [J_th] + ([np.eye(3)] if has_o else [])
            for i, J in enumerate(blocks):
                H[i] = J
        return e

    model = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sig_y, float) / math.sqrt(n))
    if huber_k:
        model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(float(huber_k)), model)
    return gtsam.CustomFactor(model, keys_, error)


def attach(sm) -> None:
    """Switch the option on for a StreamSmoother (called from its __init__): raw rows kept per interval, the
    extension appended to its end-of-stream list."""
    sm._hist_raw = []
    sm._end_extensions.append(EndWindows(sm))


def end_calibration(sm, base):
    """The calibration the end graph of a finished StreamSmoother used (`windows_end`), as a Calibration: `base` (the
    rest: gyro bias, noise, lag, std, ...) with θ = (D, o, dip) the end θ — the end solution's θ when it was free
    (windows_end="theta" with a modelled window), else θ_n, the held θ the factors used (module docstring) — and
    `disturbances` = the END windows only in the batch's format (Window.as_dict): a modelled window with its FINAL
    Δo_w (the end LM's value) and its left-out margin rows (`left_out`), an unexplained one `modelled: false`. The
    start calibration's windows are not kept (the end graph does not apply them). Calibration.corrected then gives
    the field of eq. (1): y_j − Δo_w in a modelled window, no sample where left out. None when the option did not
    rebuild the end graph (off, no θ state, skipped) or before `finish`."""
    ext = end_windows(sm)
    if ext is None or getattr(sm, "_final", None) is None:
        return None
    return ext.calibration(sm._final, base)


def end_windows(sm):
    """sm's EndWindows extension when it rebuilt the end graph's magnetometer factors (θ state, not skipped), else
    None."""
    ext = next((e for e in getattr(sm, "_end_extensions", ()) if isinstance(e, EndWindows)), None)
    return None if ext is None or ext._theta is None or "skipped" in ext.report else ext


class EndWindows:
    """The end-graph extension (graph, values) → (graph, values) of the module docstring; after the call `windows`
    holds the end windows (calibration.disturbance.Window, sample indices into `t`), `t` the sample times and `report`
    a summary (times, verdicts, offsets)."""

    def __init__(self, sm):
        self.sm = sm
        self.windows: list[Window] = []
        self._theta = None
        self._theta_free = False            # windows_end="theta" and a window modelled (on trial): θ a variable
        self._freed = False                 # θ's value moved to θ_n (once)
        self.t = np.zeros(0)
        self.report: dict = {}

    # ---------------------------------------------------------------- the stream's data
    def _theta_normal(self) -> np.ndarray:
        """θ of the end factors with the normal state's hard iron o_n (module docstring)."""
        sm = self.sm
        D, o, dip = unpack_theta(sm._end_theta())
        if sm._streamed_cal is not None and sm._theta_end is not None:   # o + Δo_w of the majority (or o itself)
            o = np.asarray(sm._streamed_cal.o, float)
        return pack_theta(D, o, dip)

    def _samples(self, values, theta: np.ndarray) -> tuple:
        """Per sample of the closed intervals: nRb_j = R_k kRb_j (N, 3, 3) and n(δ) + d_k (N, 3) at `values`, θ."""
        sm, (_, _, dip) = self.sm, unpack_theta(theta)
        n_vec = np.array([math.cos(dip), 0.0, -math.sin(dip)])
        R, n = [], []
        for k, q in enumerate(sm._hist_kRb):
            R.append(values.atPose3(pose_key(k)).rotation().matrix() @ quat_to_rotmat(q))
            d = values.atVector(field_key(k)) if sm._field else 0.0
            n.append(np.broadcast_to(n_vec + d, (len(q), 3)))
        return np.concatenate(R), np.concatenate(n)

    # ---------------------------------------------------------------- the graph
    def _base(self, graph, drop_pin: bool = False) -> gtsam.NonlinearFactorGraph | None:
        """`graph` without the end magnetometer factors of `_final_graph` (CustomFactors on one pose, at most its
        d_k and a causal Δo_w); None when their count is not the one the stream issued (an earlier extension changed
        them: the end graph is then left as it is). drop_pin: also without θ's pin (θ free)."""
        sm = self.sm
        w = ord("w")
        out, dropped = gtsam.NonlinearFactorGraph(), 0
        for i in range(graph.size()):
            if not graph.exists(i):
                continue
            f = graph.at(i)
            if drop_pin and isinstance(f, gtsam.PriorFactorVector) and list(f.keys()) == [CAL_KEY]:
                continue                   # θ's pin (stream_online._add_cal_state): replaced in _graph
            if isinstance(f, gtsam.CustomFactor):
                ks = [gtsam.Symbol(key) for key in f.keys()]
                k = ks[0].index() if ks and ks[0].chr() == ord("x") else None
                rest = [s for s in ks[1:] if not (s.chr() == w or (s.chr() == ord("f") and s.index() == k))]
                if k is not None and not rest and k in sm._mag_index:
                    dropped += 1
                    continue
            out.add(f)
        return out if dropped == len(sm._mag_index) else None

    def _labels(self) -> np.ndarray:
        """Per sample: NORMAL, LEFT_OUT or the index of its modelled window (eq. 1)."""
        lab = np.full(len(self.t), NORMAL)
        for i, w in enumerate(self.windows):
            if w.explained and w.offset is not None:
                lab[w.start:w.stop] = i
                if w.drop is not None:
                    lab[w.drop] = LEFT_OUT
            else:
                lab[w.start:w.stop] = LEFT_OUT
        return lab

    def _graph(self, base, values) -> gtsam.NonlinearFactorGraph:
        """base + every interval's magnetometer factors split by label (eq. 1); Δo_w keys inserted into `values`.
        With θ free (`_theta_free`): the factors on θ, the pin replaced by the weak prior Λ_w about θ_n."""
        sm = self.sm
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(base)
        lab = self._labels()
        prior = gtsam.noiseModel.Isotropic.Sigma(3, OFFSET_PRIOR_REL * sm._online_scale)
        if self._theta_free:
            if not values.exists(CAL_KEY):
                values.insert(CAL_KEY, self._theta)
            weak = gtsam.noiseModel.Diagonal.Sigmas(sm._weak_sig)     # Λ_w (stream_calstate eq. 4), about θ_n
            graph.add(gtsam.PriorFactorVector(CAL_KEY, self._theta.copy(), weak))
        for i, w in enumerate(self.windows):
            key = gtsam.symbol("w", END_KEY0 + i)
            if w.explained and w.offset is not None:
                if not values.exists(key):
                    values.insert(key, np.asarray(w.offset, float))
                graph.add(gtsam.PriorFactorVector(key, np.zeros(3), prior))
        start = 0
        for k, y in enumerate(sm._hist_raw):
            lk, kRb = lab[start:start + len(y)], quat_to_rotmat(sm._hist_kRb[k])
            start += len(y)
            for v in np.unique(lk[lk != LEFT_OUT]):
                y_v = np.where((lk == v)[:, None], y, np.nan)
                okey = None if v == NORMAL else gtsam.symbol("w", END_KEY0 + int(v))
                fk = field_key(k) if sm._field else None
                if self._theta_free:
                    f = theta_mag_factor(pose_key(k), fk, CAL_KEY, okey, kRb, y_v, sm._sig_y, sm.opt.huber_k)
                else:
                    f = pinned_mag_factor(pose_key(k), fk, okey, self._theta, kRb, y_v, sm._sig_y, sm.opt.huber_k)
                if f is not None:
                    graph.add(f)
        return graph

    # ---------------------------------------------------------------- rounds
    def __call__(self, graph, values):
        sm = self.sm
        if not (sm._calstate and sm.opt.keep_history and sm._mag_index and len(sm._hist_raw) == len(sm._hist_kRb)):
            return graph, values           # the end graph holds no exact θ-state factors: nothing to re-derive
        self._theta = self._theta_normal()
        D, o, _ = unpack_theta(self._theta)
        self.t, y = np.concatenate(sm._hist_t), np.concatenate(sm._hist_raw)
        m_cal = np.linalg.solve(D, (y - o).T).T
        self.windows = detect_windows(self.t, m_cal)
        base = self._base(graph)
        if base is None:
            self.report = {"rounds": 0, "skipped": "end magnetometer factors not found"}
            return graph, values
        if not self.windows:
            self.report = self._summary(0)
            return self._graph(base, values), values
        nRb, n_nav = self._samples(values, self._theta)
        # (a) offsets at iSAM2's orientations; on trial when they explain most of the window's residual
        pending = fit_offsets_on_trial(self.windows, self.t, y, nRb, D, o, n_nav, None)
        rounds = 0
        theta_mode = sm.opt.windows_end == "theta"
        if pending:                        # (b) one solve with them modelled, the verdict there
            self._theta_free = theta_mode
            values = sm._final_lm(self._graph(self._free_base(graph, base, values), values), values)
            theta = self._solved_theta(values)
            D, o, _ = unpack_theta(theta)
            nRb, n_nav = self._samples(values, theta)
            fit_offsets_on_trial(self.windows, self.t, y, nRb, D, o, n_nav,
                                 lambda: self._undisturbed_scale(y, nRb, n_nav, D, o))
            rounds = 1
        # θ free only with a modelled window (its samples, which the streamed θ never saw, inform D and the dip)
        self._theta_free = theta_mode and any(w.explained and w.offset is not None for w in self.windows)
        self.report = self._summary(rounds)
        return self._graph(self._free_base(graph, base, values), values), values

    def _free_base(self, graph, base, values):
        """The base graph for the current `_theta_free`: without θ's pin and θ at θ_n when free (else `base`)."""
        if not self._theta_free:
            return base
        if not self._freed:                # θ starts at θ_n (values: the pinned graph's θ̂ ≈ θ₀)
            values.update(CAL_KEY, self._theta)
            self._freed = True
        return self._base(graph, drop_pin=True)

    def _solved_theta(self, values) -> np.ndarray:
        """θ of a solve: the variable with θ free, else θ_n."""
        if not self._theta_free:
            return self._theta
        return np.asarray(values.atVector(CAL_KEY), float)

    def calibration(self, values, base):
        """`end_calibration` at the end LM's solution `values` (θ if free, each modelled window's Δo_w key)."""
        from dataclasses import replace

        D, o, dip = unpack_theta(self._solved_theta(values))
        out = []
        for i, w in enumerate(self.windows):
            d = w.as_dict(self.t)
            key = gtsam.symbol("w", END_KEY0 + i)
            if d["modelled"] and d["offset"] is not None and values.exists(key):   # eq. (1): the final Δo_w
                d["offset"] = np.asarray(values.atVector(key), float).tolist()
            out.append({**d, "window": END_KEY0 + i, "source": "stream_end"})
        return replace(base, D=np.asarray(D, float), o=np.asarray(o, float), dip_deg=float(np.rad2deg(dip)),
                       disturbances=out)

    def _undisturbed_scale(self, y, nRb, n_nav, D, o) -> float:
        """robust_scale of the residuals of the rows outside every window (calibration.rounds.undisturbed_rms)."""
        out = np.all(np.isfinite(y), axis=1)
        for w in self.windows:
            out[w.start:w.stop] = False
        return robust_scale(field_residuals(y[out], nRb[out], D, o, n_nav[out])) if out.any() else float("nan")

    def _summary(self, rounds: int) -> dict:
        """The end windows (the batch's calibration.json format) and, to compare, the causal ones the stream used:
        the start calibration's (fixed offsets or left out) and the detector's (runs of keyframes with one Δo_w)."""
        sm = self.sm
        detector = [{"t_start": float(sm._hist_t[a][0]), "t_end": float(sm._hist_t[b][-1]),
                     "window": int(gtsam.Symbol(key).index())} for key, a, b in sm._okey_runs()]
        return {"rounds": rounds, "windows": [w.as_dict(self.t) for w in self.windows],
                "start": [{key: d.get(key) for key in ("t_start", "t_end", "modelled")} for d in sm._cal0.disturbances],
                "detector": detector}
