"""The online-calibration half of `StreamSmoother` (imugraph.graphs.stream).

With StreamOptions.calib_states: θ = (vec D, o, dip) is a state of the graph (`imugraph.graphs.stream_calstate`):
θ's value and pin at keyframe 0 (`_add_cal_state`), every keyframe's magnetometer factor on (pose, d_k, θ)
(`_mag_factor`), and every calib_every_s a history row with the streamed θ and its std from iSAM2's estimate
and marginal covariance of θ (`_record_state`, stream_calstate eq. 3–6); at the end that θ is `cal`.

Default (calib_states=False): the closed-form refit on fixed orientations: which keyframe intervals are
folded into `OnlineMagCalibration`'s running sums and when, when a refit replaces the calibration of new
magnetometer factors, and the end-of-stream graph with every magnetometer factor re-issued (iSAM2).

Every keyframe interval, once its keyframe is final enough (it left the lag window, or is `calib_delay_s` old
under iSAM2), is folded in with its samples' orientations nRk·kRb_i, older ones down-weighted by
exp(−Δt/calib_memory_s) (their orientations were estimated with an older calibration); every `calib_every_s`
the closed-form refit (`imugraph.graphs.stream_calib`) is recorded in `calibration_history` and, when well
determined (all std of D, o < calib_swap_rel × field scale, and with calib_beat_start ≤ the start calibration's
std), becomes the
calibration of NEW magnetometer factors. Measured on simulation: swapping in every refit, poorly conditioned
early ones included, made D drift 20 std off the truth even from the true start (feedback through the
orientations); the dip is held at the start's by default (calib_dip=False): estimated online it drifted
0.2–0.5° off the truth with a 0.03° std (its error is absorbed by the orientations' tilt). Under iSAM2, `finish`
re-issues every magnetometer factor with the final calibration before its Levenberg–Marquardt. Noise levels,
the magnetometer lag and the start calibration's disturbance windows are kept.

Options (off by default): `disturb_detect` — causal disturbance windows (`imugraph.graphs.stream_disturb`; with the
start calibration's own windows) left out of the online calibration: not folded into the refit (an onset also flags
the pending intervals back to it), or, with θ as a state, the keyframe's factor without θ (`_init_disturb`,
`_disturb_step`); `calib_weak_prior` — when the start says D, o are not identifiable, the batch's weak prior
(`weak_prior`: D = s·I, o = 0, calibration.ml's σ) for the refit's (2) or θ's Λ_w with its centre.
`disturb_offsets` (with calib_states and disturb_detect) — each detector window its own hard-iron offset Δo_w and
the reported hard iron that of the majority of the samples seen so far (`imugraph.graphs.stream_offsets`;
`_offset_alive`, `_offset_estimate`, the swap in `_record_state`).
Measured on BROAD: docs/stream.md, "Disturbances and the weak prior online"."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from imugraph.calibration.result import Calibration
from imugraph.graphs.cpp_velocity import pose_key, robust
from imugraph.graphs.stream_calstate import (CAL_KEY, PIN_REL, WhitenessSums, cal_mag_factor, calibration_of,
                                             data_estimate, theta_of, weak_sigmas)
from imugraph.graphs.stream_field import field_key, field_mag_factor, linearized_once
from imugraph.graphs.stream_offsets import WindowOffsets, joint_estimate, offset_key, swap_hard_iron


def weak_start(cal: Calibration) -> bool:
    """D, o not identifiable (`cal.coverage["identifiable"]` False: calibrate's weak fallback)."""
    return isinstance(cal.coverage, dict) and cal.coverage.get("identifiable") is False


def weak_prior(cal: Calibration, scale: float | None) -> tuple[np.ndarray, np.ndarray] | None:
    """The batch's prior on θ when D, o are not identifiable (`cal.coverage["identifiable"]` False): centre D = s·I,
    o = 0 (`calibration.initial.weak_initial`; the dip: the start's), σ from `calibration.ml`'s `_theta_prior_sigma`
    with `Options().weak_theta_fraction` (D ± f·s, o ± 2f·s, δ ± 90°); None for an identifiable start."""
    if not weak_start(cal):
        return None
    from imugraph.calibration.ml import _theta_prior_sigma
    from imugraph.calibration.options import Options
    from imugraph.factors.theta import pack_theta

    s = float(scale) if scale else float(np.cbrt(abs(np.linalg.det(cal.D))))
    centre = pack_theta(s * np.eye(3), np.zeros(3), cal.dip_rad)
    return centre, _theta_prior_sigma(centre, True, Options().weak_theta_fraction)


class OnlineCalibrationMixin:
    """Methods of StreamSmoother that keep `self.cal` (the calibration of new magnetometer factors) up to date
    from `self._online`; state lives in StreamSmoother.__init__."""

    def _set_calibration(self, cal: Calibration) -> None:
        """The calibration of new magnetometer factors: D⁻¹, o, n_mag and the calibrated field's covariance
        D⁻¹ Σ_y D⁻ᵀ."""
        self.cal = cal
        self._D_inv = np.linalg.inv(cal.D)
        self._S_m = self._D_inv @ np.diag(self._sig_y**2) @ self._D_inv.T

    @property
    def calibration_history(self) -> list:
        """Rows {t (s since the first sample), D, o, dip_deg, std, samples, rejected, applied}, one per refit
        (`applied`: it became the calibration of new magnetometer factors; else it was not well determined).
        With θ as a graph state: one row per calib_every_s, θ's estimate and marginal std then (`applied`
        False: the orientations keep the start calibration, θ is pinned there, stream_calstate)."""
        if self._calstate:
            return self._cal_hist
        return self._online.history if self._online is not None else []

    # ------------------------------------------------------------------ θ as a graph state (stream_calstate)
    def _init_calstate(self, cal: Calibration) -> None:
        self._theta0 = theta_of(cal)         # the pin (stream_calstate eq. 3)
        self._theta_lin = self._theta0.copy()   # θ at which new magnetometer factors are linearised (eq. 5)
        self._cal_hist: list = []
        self._weak_sig = weak_sigmas(cal, self.opt.calib_prior_rel)
        self._pin_sig = PIN_REL * self._weak_sig
        self._online_scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
        self._streamed_cal = None            # latest streamed calibration (eq. 4)
        self._white = WhitenessSums()        # eq. (6)
        self._gated = 0                      # keyframes without information on θ (calib_gate)
        self._mag_okey: dict = {}            # keyframe → its window's offset key Δo_w (disturb_offsets)
        self._prior_mean = None              # of Λ_w: θ₀ (None), or the batch's weak prior centre (_init_disturb)
        self._theta_end = None               # latest streamed θ of the graph's normal state (eq. 4; calib_final_theta)
        self._end_cal = None                 # its calibration (no majority swap): calibration.json after the end graph

    # ------------------------------------------------------------------ disturbances, the weak prior
    def _init_disturb(self, cal: Calibration, weak_scale: float | None, learn_s: float = 0.0) -> None:
        """The causal disturbance detector (options.disturb_detect, stream_disturb) and, with calib_weak_prior on a
        start that says D, o are not identifiable, the batch's weak prior for the online calibration."""
        opt = self.opt
        self._disturbed: set = set()         # pending keyframes flagged (refit: not folded in)
        self._detector = None
        self._win_now = None                 # the window of the interval being closed (disturb_offsets)
        self._offsets = (WindowOffsets(self._online_scale) if opt.disturb_offsets and opt.disturb_detect
                         and opt.online_calibration and self._calstate else None)
        if opt.disturb_detect and opt.online_calibration:
            from imugraph.graphs.stream_disturb import DisturbanceDetector, field_norm_sigma

            self._detector = DisturbanceDetector(     # _online_scale: set by _init_calstate, called first
                cal.D, cal.o, field_norm_sigma(opt.field_sigma, cal.dip_rad),
                float(np.mean(self._sig_y)) / self._online_scale,
                opt.disturb_p_alarm, opt.disturb_p_drift, opt.disturb_pad_s,
                max(opt.lag_s or 0.0, opt.calib_delay_s), max(learn_s, opt.disturb_learn_s),
                learn_sigma=opt.disturb_learn_sigma)
        weak = weak_prior(cal, weak_scale) if opt.calib_weak_prior and opt.online_calibration else None
        if weak is None:
            return
        centre, sig = weak
        if self._calstate:                   # Λ_w of stream_calstate eq. (4) about the weak centre (the pin stays)
            self._weak_sig, self._prior_mean = sig, centre
        else:
            self._online.set_prior(centre, sig)

    def _disturb_step(self, k: int, t_start: float, t_end: float, y: np.ndarray, ok: np.ndarray, known: bool) -> bool:
        """Interval k through the detector; flags it (and, at an onset, the pending intervals back to it) for the
        refit's fold-in; counts. known: it overlaps one of the start calibration's own disturbance windows (its field
        is already corrected there; flagged too: the offsets were fitted with the start's D, o). Returns whether
        interval k is in a disturbance window."""
        flag, onset = self._detector.step(t_start, t_end, y)
        if self._offsets is not None:        # the detector's window (stream_offsets; the start's own keep their handling)
            self._win_now = self._detector.windows - 1 if flag and self._detector.windows and not known else None
        flag = flag or known
        st = self.stats
        st.disturbances = self._detector.windows
        if onset is not None:
            if self._online is not None:     # not yet folded in: flag them too (at most max_lag_s back)
                t_on, span = onset - self._t0, self.stride / self.rate
                for kp, tk, _, yp in self._pending:
                    if tk + span > t_on and kp not in self._disturbed:
                        self._disturbed.add(kp)
                        st.disturbed_keyframes += 1
                        st.disturbed_samples += int(np.isfinite(yp[:, 0]).sum())
        if flag:
            st.disturbed_keyframes += 1
            st.disturbed_samples += int(ok.sum())
            if self._online is not None:
                self._disturbed.add(k)
        return flag

    def _add_cal_state(self, graph, values, stamps) -> None:
        """θ's value and pin at keyframe 0."""
        values.insert(CAL_KEY, self._theta0)
        graph.add(gtsam.PriorFactorVector(CAL_KEY, self._theta0.copy(), gtsam.noiseModel.Diagonal.Sigmas(self._pin_sig)))
        stamps[CAL_KEY] = 0.0

    def _offset_alive(self, key: int) -> bool:
        """A window offset's key is still in the solver (the chain lag marginalises the others)."""
        return key in self._solver.stamps if self._chain else True

    def _offset_estimate(self, key: int):
        """The solver's latest estimate of a window offset Δo_w, None when it has left the solver."""
        if not self._offset_alive(key):
            return None
        return self._isam().calculateEstimateVector(key)

    def _end_theta(self) -> np.ndarray:
        """θ of the end graph's exact magnetometer factors: the streamed θ (stream_calstate eq. 4, the flush's row)
        with calib_final_theta, as the batch smooths with the θ it estimated (docs/stream.md "Session 17, helper L");
        else (or before any record) the pin θ₀."""
        return self._theta_end if (self.opt.calib_final_theta and self._theta_end is not None) else self._theta0

    def _record_state(self, elapsed: float) -> None:
        """A history row: the streamed θ and its std (stream_calstate eq. 4) from iSAM2's θ̂ and marginal covariance;
        with disturb_offsets, when a window is the majority, its hard iron (stream_offsets eq. 2)."""
        self._refit_due = False
        isam = self._isam()
        major = self._offsets.majority(self._offset_alive) if self._offsets is not None else None
        try:
            theta, cov = data_estimate(isam.calculateEstimateVector(CAL_KEY), isam.marginalCovariance(CAL_KEY),
                                       self._theta0, self._pin_sig, self._weak_sig, self._prior_mean)
            if major is not None:       # θ and Δo_w jointly; reported: o + Δo_w
                okey = offset_key(major)
                J = isam.jointMarginalInformation(gtsam.KeyVector([CAL_KEY, okey]))
                J = np.block([[J.at(CAL_KEY, CAL_KEY), J.at(CAL_KEY, okey)], [J.at(okey, CAL_KEY), J.at(okey, okey)]])
                psi, cov_psi = joint_estimate(np.r_[isam.calculateEstimateVector(CAL_KEY), isam.calculateEstimateVector(okey)],
                                              J, self._theta0, self._pin_sig, self._weak_sig, self._prior_mean)
                rep, cov_rep = swap_hard_iron(psi, cov_psi)
        except (RuntimeError, np.linalg.LinAlgError):       # counted as a failed update; no row
            self.stats.failed_updates += 1
            return
        self._theta_end = theta              # before the majority swap: the normal state's streamed θ (calib_final_theta)
        cov_end = cov
        white = calibration_of(self.cal, theta, cov).std
        if max(np.max(white["D"]), np.max(white["o"])) < self.opt.calib_lin_rel * self._online_scale:
            self._theta_lin = theta          # well determined: new factors linearised there (stream_calstate eq. 5)
        if major is not None:                # what is reported (the graph's θ keeps the start's normal state)
            theta, cov = rep, cov_rep
            white = calibration_of(self.cal, theta, cov).std
        self._white.end_block()
        V = self._white.factor(self._theta0)        # eq. (6): std of row j of D and o_j × √max(1, V_j)
        if V is not None:
            f = np.sqrt(np.maximum(V, 1.0))
            s = np.r_[np.repeat(f, 3), f, f.max()]
            cov = cov * s[:, None] * s[None, :]
            cov_end = cov_end * s[:, None] * s[None, :]
        cal = self._streamed_cal = calibration_of(self.cal, theta, cov)
        # the end graph's calibration (normal state, no swap; `_end_calibration`): the streamed one without a majority
        self._end_cal = cal if major is None else calibration_of(self.cal, self._theta_end, cov_end)
        self._cal_hist.append({"t": float(elapsed), "D": cal.D.tolist(), "o": cal.o.tolist(), "dip_deg": cal.dip_deg,
                               "std": {"D": cal.std["D"].tolist(), "o": cal.std["o"].tolist(), "dip_deg": cal.std["dip_deg"]},
                               "whiteness": None if V is None else V.tolist(),
                               "std_white": {"D": white["D"].tolist(), "o": white["o"].tolist(), "dip_deg": white["dip_deg"]},
                               "samples": float(self._k), "rejected": int(self._gated), "applied": False,
                               **({} if self._offsets is None else self._offsets.row(major))})
        self.stats.calib_refits += 1

    def _keyframe_R(self, k: int) -> np.ndarray | None:
        """Latest estimate of keyframe k's nRb (the one it left the window with, under a lag)."""
        if self.opt.lag_s is not None and (not self._chain or k in self._smoothed_kf):
            return self._smoothed_kf.get(k)
        try:           # iSAM2, or a keyframe still in the chain lag's window
            return self._isam().calculateEstimatePose3(pose_key(k)).rotation().matrix()
        except RuntimeError:
            return None

    def _calibrate(self, elapsed: float, flush: bool = False) -> None:
        """Fold in the intervals whose keyframe is final enough; refit every calib_every_s (see stream_calib)."""
        delay = max(self.opt.calib_delay_s, self.opt.lag_s or 0.0)
        while self._pending and (flush or self._pending[0][1] < elapsed - delay):
            k, _, kRb, y = self._pending.popleft()
            nRk = self._keyframe_R(k)
            if self.opt.calib_memory_s:      # w = exp(−Δt/T) per interval
                self._online.forget(float(np.exp(-self.stride / self.rate / self.opt.calib_memory_s)))
            if k in self._disturbed:         # a disturbance window (stream_disturb): not used
                self._disturbed.discard(k)
            elif nRk is not None:
                # without d_k: folding the graph's d_k in kept the start calibration's error (d absorbs it, ~1 %
                # of the field, within σ_d) — simulation, tests/test_stream_calib.py: D 16 std off the truth
                self._online.add(y, nRk @ kRb)       # nRb_i = nRk · kRb_i
        if flush or elapsed >= self._next_refit:
            self._next_refit = elapsed + self.opt.calib_every_s
            if flush or not self._mid:
                self._refit(elapsed, flush)
            else:       # on the next sample between keyframes (StreamSmoother._between_keyframes): same data
                self._refit_due = True

    def _refit(self, elapsed: float, flush: bool = False) -> None:
        """A refit recorded in the history, and the calibration of new magnetometer factors when well determined
        (with θ as a graph state: `_record_state`)."""
        if self._calstate:      # at the end the streamed calibration becomes `cal` (calibration.json)
            self._record_state(elapsed)
            if flush and self._streamed_cal is not None:
                self.cal = self._streamed_cal
            return
        self._refit_due = False
        cal = self._online.refit(elapsed)
        # swap in only a well-determined refit: a poorly conditioned early one would bias the next
        # orientations, which feed the next refit (measured on simulation: D drifted 20 std off the truth)
        # judged on the reported std (with the whiteness factor, stream_calib eq. 3), or with
        # calib_swap_white on the white-noise one
        std = self._online.std_white if self.opt.calib_swap_white else cal.std
        applied = bool(self.opt.calib_swap and cal.std and self._online.std_white is not None
                       and self._well_determined(std))
        if applied:
            self._set_calibration(replace(self.cal, D=cal.D, o=cal.o, dip_deg=cal.dip_deg, std=cal.std))
        self._online.history[-1]["applied"] = applied
        self.stats.calib_refits += 1

    def _well_determined(self, std: dict) -> bool:
        """All of the refit's D and o std below calib_swap_rel × field scale (and below the start
        calibration's own std where it has one)."""
        worst = max(np.max(std["D"]), np.max(std["o"])) / self._online.scale
        if worst > self.opt.calib_swap_rel:
            return False
        s0 = self._online.cal0.std
        return not s0 or not self.opt.calib_beat_start or (np.all(np.asarray(std["D"]) <= np.asarray(s0.get("D", np.inf)))
                          and np.all(np.asarray(std["o"]) <= np.asarray(s0.get("o", np.inf))))

    def _mag_factor(self, k: int, kRb: np.ndarray, y: np.ndarray, exact: bool = False, no_theta: bool = False,
                    into: tuple | None = None):
        """Huber MagPoseFactorPose3 on keyframe k: the interval's calibrated field D⁻¹(y − o) rotated into
        keyframe k and averaged (full covariance), against the current n_mag. With the field perturbation:
        stream_field's factor against n + d_k, linearised once at keyframe k's latest estimate (exact=False,
        for the incremental solvers; see stream_field.linearized_once) or the exact CustomFactor. no_theta: with θ as a
        graph state, the factor carries no information on θ (a disturbance window: gated as by calib_gate); with
        disturb_offsets and a window (`_win_now`) instead on (pose_k, d_k, θ, Δo_w) (stream_offsets), its key and prior
        added through into = (graph, values, stamps, now) when new."""
        if self._calstate and exact:     # the end-of-stream graph: exact at the pin θ₀, d_k and Δo_w free
            from imugraph.graphs.stream_calstate import pinned_mag_factor

            return pinned_mag_factor(pose_key(k), field_key(k) if self._field else None, self._mag_okey.get(k),
                                     self._end_theta(), kRb, y, self._sig_y, self.opt.huber_k)
        if self._calstate:       # on (pose_k, d_k, θ), linearised once (stream_calstate eq. 1–2)
            offs = self._offsets
            win = self._win_now if (no_theta and offs is not None) else None
            if win is not None:      # its own hard-iron offset (stream_offsets eq. 1), still no information on θ
                okey, olin = offs.key_of(win, self._offset_estimate)
            else:
                okey = olin = None
            gate = -1.0 if no_theta else None if self.opt.calib_gate is None else self.opt.calib_gate * self._online_scale
            info = {} if offs is not None else None
            f, rows = cal_mag_factor(pose_key(k), gtsam.Pose3(self._nRk, self._p), field_key(k) if self._field else None,
                                     self._d, self._theta_lin, kRb, y, self._sig_y, self.opt.huber_k, self._theta0, gate,
                                     okey, olin, info)
            if win is not None:
                if f is not None:
                    offs.added(win, info["offset"], info["n"], info["r2"], *into)
                    self._mag_okey[k] = okey          # for the exact re-issue at the end (_final_graph)
            elif rows is not None:
                self._white.add(*rows)
                if offs is not None:
                    offs.normal(info["n"], info["r2"])
            else:
                self._gated += 1
            return f
        m_cal = (y - self.cal.o) @ self._D_inv.T
        ok = np.all(np.isfinite(m_cal), axis=1)
        R, m_ok = (kRb, m_cal) if ok.all() else (kRb[ok], m_cal[ok])
        n_ok = len(R)
        m_avg = np.einsum("mij,mj->i", R, m_ok) / n_ok                      # mean of kRb_i m_i
        cov = np.einsum("mij,mkj->ik", R @ self._S_m, R) / n_ok**2          # Σ_i kRb_i S_m kRb_iᵀ / n²
        mdl = robust(gtsam.noiseModel.Gaussian.Covariance(cov), self.opt.huber_k)
        if self._field:          # against n + d_k (imugraph.graphs.stream_field eq. 3)
            f = field_mag_factor(pose_key(k), field_key(k), m_avg, self.cal.n_mag, mdl)
            return f if exact else linearized_once(f, pose_key(k), gtsam.Pose3(self._nRk, self._p), field_key(k), self._d)
        return gtsam.MagPoseFactorPose3(pose_key(k), m_avg, 1.0, self.cal.n_mag, np.zeros(3), mdl)
