"""Settings and counters of an incremental run (imugraph.graphs.stream)."""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field

import gtsam
import numpy as np

from imugraph.calibration.disturbance import PAD_S
from imugraph.errors import SessionError
from imugraph.factors.gaps import GAP_ACC_WALK, GAP_RATE_WALK


@dataclass(frozen=True)
class StreamOptions:
    """Settings of a stream (defaults: those of `smooth_fixed`).

    Attributes:
        keyframe_hz: keyframes per second (stride = round(rate / keyframe_hz) samples).
        lag_s: None: iSAM2 over the whole stream; a number: fixed-lag smoother keeping lag_s seconds.
        fixed_lag_solver: with lag_s, "chain" (default: `imugraph.graphs.stream_lag.ChainLagSmoother`, iSAM2 with the
            keyframes eliminated in time order, marginalising every lag_hold_s between keyframes: the window holds lag_s to lag_s + lag_hold_s),
            "incremental" (gtsam.IncrementalFixedLagSmoother, iSAM2 inside; with the weak pose prior and the iSAM2
            settings in both) or "batch" (gtsam.BatchFixedLagSmoother). With the field perturbation "chain" costs
            ≈ 2.5× less per update than "incremental" (stream_lag); earlier, without it, on BROAD 01 / 02 (2 s,
            online calibration): incremental filtered 2.59 / 0.63°, 27–30× real time in CPU time, against batch
            2.62 / 0.65°, 10–19×, one failed update each.
        g: gravity, m/s², held fixed; None: estimated (started at `g0`, the caller's median |acc|).
        final_updates: relinearising iSAM2 updates at `finish` (iSAM2 only).
        relinearize_threshold: iSAM2's relinearisation threshold (tangent-space step).
        keep_history: keep per-sample data for `smoothed()` (memory O(N)); False: filtered output only.
        online_calibration: re-estimate D and o (the dip with calib_dip) online (`imugraph.graphs.stream_calib`); False:
            the calibration is held fixed.
        calib_every_s: stream seconds between refits; calib_delay_s: a keyframe's samples are folded in once
            it is this old (at least the lag with a fixed-lag smoother); calib_prior_rel: σ of the prior about
            the start calibration, relative to the field scale (calib_prior_from_start: the start's own std
            where it has one, e.g. a bootstrap's); calib_memory_s: time constant of the exponential forgetting
            of folded samples (None: none); calib_every_s refits; calib_swap: a well-determined refit (all std
            of D, o < calib_swap_rel × scale; with calib_beat_start also ≤ the start's std) becomes the
            calibration of new magnetometer factors — judged on the reported std, which carries the residuals'
            whiteness factor (stream_calib eq. 3), or with calib_swap_white on the white-noise std; calib_dip:
            re-estimate the dip too (off: it drifted on simulation, see stream_online).
        calib_states: with online_calibration under iSAM2 or the chain lag, θ = (D, o, dip) is a state of the
            graph in every magnetometer factor, pinned at the start calibration, and the streamed calibration is
            what the data say about it jointly with the orientations (`imugraph.graphs.stream_calstate` eq. 3–4,
            weak prior calib_prior_rel × scale; the filtered orientations keep the start calibration, the end-of-stream
            smoothing uses the streamed one with calib_final_theta); the refit options
            above then do not apply. True (default since session 14, with disturb_detect and disturb_offsets: all 17
            BROAD trials within 3 reported std of the batch calibration, filtered 1.27° vs 1.45°; README, issue 3).
            False: the closed-form refit on fixed orientations (stream_calib), whose swapped-in refits do reach
            the orientations (10/17 within 3 std).
            calib_lin_rel: once every std of the streamed D, o is below calib_lin_rel × field scale, new
            magnetometer factors are linearised at the streamed θ (stream_calstate eq. 5; 0: never). calib_gate:
            a keyframe whose mean field residual exceeds calib_gate × field scale gives no information on θ
            (a disturbance; None: every keyframe), as the refit's sample gate.
        factorization: of iSAM2 (also inside the incremental fixed lag), "QR" or "CHOLESKY". QR by default: on
            BROAD 30 (bootstrap dip 86°: a nearly vertical field) Cholesky threw IndeterminantLinearSystem at the
            first update and then at every later one (1726 of 1750 with the incremental lag: the output was
            dead reckoning); QR solved every update (the trial's 77° error then was its bad bootstrap, see
            stream_run.bootstrap_calibration), for ≈ 10 % more CPU (BROAD 01, 60 s: incremental
            lag 34.1× → 30.9× real time in CPU time, iSAM2 18.6× → 16.6×; filtered error unchanged).
        lag_hold_s: the chain lag marginalises every lag_hold_s (the window holds lag_s to lag_s + lag_hold_s): a
            marginalisation re-eliminates the window, on a sample between keyframes (StreamSmoother._between_keyframes);
            BROAD 01 / 34, first 150 s, CPU (load ≈ 5): 1 s → 0.5 s, p99 of the between-keyframe steps 5.4 / 5.0 →
            4.0 / 4.4 ms, filtered unchanged (2.18 / 3.99°), lag-smoothed 1.99 / 3.52 → 2.01 / 3.55°.
        field_sigma, field_tau: the nav-field Gauss–Markov perturbation d_k per keyframe of the batch model
            (imugraph.factors.field, `calibration.ml.Options`' defaults; σ_d per nav axis, x along the horizontal
            field, y across it, z up; τ_d s); magnetometer factors use n + d_k (`imugraph.graphs.stream_field`).
            None: no perturbation (the field is n_mag exactly, as `smooth_fixed`).
        velocity_sigma, velocity_tau: σ_v (m/s), τ_v (s) of the bounded-velocity process; None: the calibration's
            estimate (`Calibration.velocity_sigma/tau`, calibration/velocity_process.py), else 0.5 m/s / 2 s — as
            `smooth_fixed` chooses them.
        acc_lead_samples: δ ≥ 0, accelerometer row j paired with the strapdown orientation of row j + δ
            (calibration/acc_timing.py eq. 3, applied causally per interval: StreamSmoother._lead); None: the
            calibration's `acc_lead_samples` (0.5 from `calibrate`), as `smooth_fixed` chooses it.
        disturb_detect: detect lasting magnetometer disturbances causally (`imugraph.graphs.stream_disturb`: a CUSUM
            on the whitened norm deviation of the field calibrated with the start calibration, thresholds from χ²₁
            quantiles disturb_p_alarm / disturb_p_drift, windows widened by disturb_pad_s; the field's own variation
            learned over the bootstrap window, at least disturb_learn_s) and leave their intervals
            out of the online calibration (the refit's fold-in; with calib_states their factors carry no θ);
            counted in `StreamStats` (disturbances, disturbed_keyframes, disturbed_samples). disturb_orient: also
            leave the magnetometer factor of a flagged keyframe out of the orientations (decided when its interval
            closes). On by default since session 14 (docs/stream.md, "Disturbances and the weak prior online").
        disturb_offsets: with calib_states and disturb_detect, each disturbance window (the detector's and the start
            calibration's modelled ones) gets its own hard-iron offset Δo_w as the batch's, so that its keyframes
            inform D and the dip, and the reported hard iron is that of the majority of the samples seen so far
            (`imugraph.graphs.stream_offsets`). On by default since session 14 (docs/stream.md, "Windowed offsets and the
            majority").
        calib_weak_prior: when the start calibration says D, o are not identifiable (`coverage["identifiable"]`
            False: the regularised fallback of `calibrate`), the online calibration's prior is the batch's weak
            prior — D = s·I, o = 0 with σ = weak_theta_fraction × s (o: twice), `calibration.ml`'s — instead of the
            start ± calib_prior_rel (or the start's own std); s is `StreamSmoother`'s weak_scale (stream_session:
            median |y| over the bootstrap window, as `calibration.initial.weak_initial`).
        Other fields: as `smooth_fixed`.
    """

    keyframe_hz: float = 10.0
    lag_s: float | None = None
    fixed_lag_solver: str = "chain"
    g: float | None = None
    huber_k: float = 2.0
    gyro_rate_error: float = 0.01
    velocity_sigma: float | None = None
    velocity_tau: float | None = None
    acc_lead_samples: float | None = None
    acc_rate_error: float = 0.01
    # samples that never arrived (a step > 1.5 nominal steps): the held rate and specific force are trusted as a
    # random walk of these densities over the missing time (imugraph.factors.gaps eq. G1, as the batch path);
    # 0: trusted like measured time. No effect on a stream without gaps.
    gap_rate_walk: float = GAP_RATE_WALK
    gap_acc_walk: float = GAP_ACC_WALK
    # after a gap that starts a keyframe, the rotation about the magnetic field re-solved from the first
    # gap_realign_s seconds of integrated specific force (stream_realign eq. R1–R3); when |α*| > gap_realign_gate σ_α
    # the gap's rotation rows are removed and the keyframe closing that window is pinned there about n̂ (σ
    # gap_realign_pin_deg) for gap_realign_hold updates. None: off (chain lag and iSAM2 only). No effect on a stream
    # without gaps. A partial fix (docs/gaps.md "Task G": BROAD 06, 3 × 0.5 s: 37.4° → 25.2° filtered).
    gap_realign_s: float | None = None
    gap_realign_gate: float = 3.0
    gap_realign_pin_deg: float = 1.0
    gap_realign_hold: int = 3
    gap_realign_keep: bool = False     # also a lasting one-axis prior of σ_α (eq. R3) at the same rotation
    # a bounded keyframe position p_k (stream_position eq. K1–K3: p_{k+1} = p_k + v_k Δt, stationary Gauss–Markov
    # prior σ_p m, τ_p s; the batch's velocity_block (P1)), marginalised with the keyframe. None: off (task K,
    # docs/gaps.md "Session 17, helper K").
    position_sigma: float | None = None
    position_tau: float = 30.0
    # candidate σ_p (m, 1e4 = "off") chosen by the bootstrap batch (calibration.position_select eq. J2, with
    # position_select_rounds) and used as position_sigma for the stream (stream_run.select_position; only when
    # stream_session bootstraps itself: ignored with a given calibration or bootstrap). None: off (position_sigma as
    # given). Not safe on a travelling sensor: a 30 s walk window chooses 1 m on 2 of 4 simulated walks
    # (docs/gaps.md "Session 17, helper K2").
    position_select: tuple | None = None
    # the rate and specific force across a gap bridged to the first sample after it (stream_bridge eq. B1, variance
    # q² τ³/12, B2) instead of held (G1). False: held, as the batch path.
    gap_bridge: bool = False
    acc_huber_k: float | None = 2.0
    acc_bias_sigma: float = 1e-4
    bias_segment_s: float = 5.0
    bias_rw: float = 2e-4
    bias_prior_sigma: float = 0.01
    final_updates: int = 3
    relinearize_threshold: float = 0.01
    factorization: str = "QR"
    keep_history: bool = True
    online_calibration: bool = True
    calib_every_s: float = 2.0
    calib_delay_s: float = 2.0
    calib_prior_rel: float = 0.2
    calib_swap: bool = True
    calib_dip: bool = False
    calib_prior_from_start: bool = True
    calib_beat_start: bool = False
    calib_memory_s: float | None = 20.0
    calib_swap_rel: float = 0.002
    calib_swap_white: bool = False
    calib_states: bool = True          # default since session 14 (README, docs/stream.md)
    calib_lin_rel: float = 0.01
    calib_gate: float | None = 0.3
    # with calib_states under iSAM2 (keep_history): the end-of-stream graph's magnetometer factors at the streamed θ
    # (stream_calstate eq. 4, at the flush) instead of the pin θ₀ — the smoothed output with the calibration the stream
    # estimated, as the batch smooths with its own; the filtered output unchanged. False: θ₀ (docs/stream.md
    # "Session 17, helper L"). Default since session 17: smoothing at the pin θ₀ left the end result at the start
    # calibration (simulation with θ₀ 3 % off: smoothed 1.72° → 0.17°; BROAD 17 vs the batch with d_k 0.447 → 0.348°,
    # vs truth 0.777° both).
    calib_final_theta: bool = True
    # with calib_final_theta's end graph: calibration.json (StreamSmoother.cal after finish) holds what it used — the
    # normal state's streamed θ and each detector window's final Δo_w as a modelled `disturbances` entry — instead of
    # the majority swap's o without windows, so `smooth --calibration` reproduces the smoothed output (R4 scenario:
    # 6.71° → 0.006°; tests/test_stream_calibration_json.py, docs/stream.md "Session 17, helper M1"). False: before.
    # With windows_end: stream_windows_end.end_calibration (helper W2). Default since session 18: with the end windows
    # the majority swap's calibration.json no longer described the end graph (BROAD 32: smooth --calibration 79° from
    # the stream's smoothed output; with it 0.25°).
    calib_json_end_graph: bool = True
    field_sigma: float | tuple | None = (0.015, 0.003, 0.015)
    field_tau: float = 1.0
    lag_hold_s: float = 0.5
    disturb_detect: bool = True
    disturb_p_alarm: float = 1e-4
    disturb_p_drift: float = 0.01
    disturb_pad_s: float = PAD_S       # the batch's window padding (calibration.disturbance)
    disturb_learn_s: float = 10.0
    # σ_f of stream_disturb eq. (1) learned over the bootstrap window (True, the robust RMS of ē_k about 0), or
    # False: the floor only (the batch's MIN_THRESHOLD: a sustained 6 % deviation never accumulates). A start that
    # misfits its own rows (BROAD 36: −5.5 % at rest, +8 % in motion) inflates the learned σ_f (0.08) past every
    # later disturbance; benchmarks/a_cal_verdict.py, docs/stream.md "Task A".
    # (default False since session 16: 17/17 BROAD trials within 3 std of the batch, filtered mean 1.30 → 1.33°)
    disturb_learn_sigma: bool = False
    disturb_orient: bool = False
    disturb_offsets: bool = True
    calib_weak_prior: bool = False
    # session 18 (helper W): the end graph's (full iSAM2, keep_history) disturbance windows re-derived from the whole
    # stream with the batch's detector and trial verdict instead of the causal ones (stream_windows_end); "theta": also
    # θ = (D, o, dip) free in the end graph when a window is found (the window samples inform D, dip). False: before.
    # The three end-graph extensions are the default since session 18 (17 BROAD trials, stream vs batch with d_k
    # 0.348 → 0.171° mean, vs truth 0.777 → 0.646°: benchmarks/stream_vs_batch.py all --config default,end_all)
    windows_end: bool | str = "theta"
    # session 18 (helper V): the end graph's (full iSAM2, keep_history) velocity process σ_v, τ_v re-estimated by EM from
    # the stream's own velocities with the batch's M-step and bounds (stream_velocity): "ar2_batch_id" (the batch's AR(2)
    # fit at the batch's 5-Hz keyframe spacing, first-order equivalent, kept unless both variance bounds decide it; also
    # "ar2_batch_em", "ar2_batch", "ar2", "gm"); "off": the start calibration's process, as before.
    velocity_end: str = "ar2_batch_id"
    # session 18 (helper E): the end graph (full iSAM2, keep_history) estimates the gyro map E jointly with the
    # orientations, with the batch's gates (clean turns ≥ 15) and settling fallback (stream_gmap); "split": also kept
    # only when the two halves' clean intervals give the same E (stream_gmap.split_check); "batch_clean": E informed by
    # the batch's 0.2 s clean intervals only (stream_gmap.clean_as_batch). "exact" (session 19, helper Z): each round
    # re-preintegrates every interval's kept samples at the current Ê and bias with the batch's code (stream_gmap
    # eq. 3; 6 floats per sample kept); "exact_batch_clean": both; "theta" (diagnostic): θ free in the E rounds, as
    # the batch's (stream_windows_end's θ-free factors); "theta_gate": those rounds as the settling gate only;
    # "theta_e" (helper Z2): their Ê applied in the default's θ-held end graph (04 0.504 → 0.269°, 02 0.106 → 0.156° from
    # the batch; opt-in). False: the start's E. Default "theta_gate" since session 19 (the lead, on helper Z's numbers: BROAD 24 falls back like
    # the batch, 0.303 → 0.035° from it; 01/02/04 identical; True before).
    gyro_map_end: bool | str = "theta_gate"
    # session 19 (helper Y): the end graph (full iSAM2, keep_history) re-estimates the magnetometer noise σ_m with the
    # batch's estimator (calibration.noise.reestimate on the stream's per-sample rows at the end solution, its dof
    # corrections, the batch's round thinning), rebuilds the magnetometer factors and re-solves until σ_m moves <
    # Options().noise_tol (stream_noise; after windows_end, before velocity_end); calibration.json carries σ̂_m.
    # Σω, Σa stay the start's (the batch takes them from its rest detector). False: the start's σ_m, as before.
    noise_end: bool = False
    # session 19 (helper D): the end graph (full iSAM2, keep_history) re-estimates the magnetometer's lag behind the gyro
    # on the whole stream with the batch's estimator (alignment.estimate_mag_delay on the start-calibrated field and the
    # per-sample gyro rates recovered from the kept rotations); when round(τ̂·rate) differs from the bootstrap's shift,
    # every interval's magnetometer rows are re-paired and the end graph's exact magnetometer factors rebuilt (stream_
    # delay_end; the first end extension: windows_end and noise_end see the re-paired rows); calibration.json carries
    # τ̂ as mag_delay_s. "clean": τ̂ from the normal state's rows only (the start windows and the causal detector's window
    # keyframes left out). False: the bootstrap's lag. True: on BROAD 26 0.151 → 0.048°, 04 0.504 → 0.435° from the
    # batch, 15 of 17 bit for bit unchanged — but on a simulated magnet that comes off (tests/test_stream_same_model.py's
    # session) τ̂ is −12.7 ms (lag 0), the rows are re-paired by −1 and the smoothed error goes 0.170 → 1.088°
    # (benchmarks/d19_magnet_off.py); "clean" gets that case right but takes BROAD 34 to the wrong shift (vs truth
    # 0.736 → 0.910°).
    # "guarded" (helper G): τ̂ as True, but s₁ kept only if the end graph solved with s₁'s rows has a lower total cost
    # than with s₀'s (stream_delay_end eq. 3): the magnet case keeps 0 (F 365 vs 1180); BROAD 26 kept, 04 not.
    # Default "guarded" since session 19 (the lead): 26 0.151 → 0.048° from the batch; the other 16 BROAD trials
    # unchanged (the shift is the start's on 13, 04's guard keeps s₀, 32's re-pairing is skipped); True as before.
    mag_delay_end: bool | str = "guarded"
    # session 22 (helper F22a): a lagging magnetometer's fields that arrive after their interval closed (its last s₀
    # rows' fields: counts.mag_dropped) go into the next keyframe's magnetometer factor, rotated by the closed interval's
    # own rotations (stream_carry eq. C1), and into the closed interval's kept rows for the end graph. False: dropped.
    mag_carry: bool = False


@dataclass
class StreamStats:
    """Counters of what arrived, and the wall time of every solver update (s; an array('d'), 8 bytes each) and
    its CPU time (this thread's: what a loaded, shared machine does not inflate)."""

    accepted: int = 0
    duplicates: int = 0
    late_inserted: int = 0
    late_dropped: int = 0
    invalid: int = 0
    gaps: int = 0
    missing: int = 0
    mag_samples: int = 0
    mag_dropped: int = 0
    failed_updates: int = 0
    marginal_steps: int = 0
    calib_refits: int = 0
    disturbances: int = 0
    disturbed_keyframes: int = 0
    disturbed_samples: int = 0
    update_s: array = field(default_factory=lambda: array("d"))
    update_cpu_s: array = field(default_factory=lambda: array("d"))
    between_s: array = field(default_factory=lambda: array("d"))
    between_cpu_s: array = field(default_factory=lambda: array("d"))

    def counts(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if not isinstance(v, array)}


# σ of the weak pose prior added with every new keyframe (rad and m: information 1e-6 against ~1e9 of the
# gyro rows). Without it gtsam's Cholesky throws IndeterminantLinearSystem at EVERY iSAM2 update of this
# graph (measured on BROAD 01: 1964 of 1964 updates failed, the filtered output was then gyro dead
# reckoning, 7.4° RMS); any one weakly constrained direction of the new pose suffices, QR works too but
# is 3× slower. The batch path never saw it: Levenberg–Marquardt's damping regularises the same system.
SIGMA_WEAK_POSE = 1e3


def make_solver(options: StreamOptions):
    """The stream's solver: gtsam.ISAM2 (lag_s None) or the fixed lag `options.fixed_lag_solver` ("chain":
    imugraph.graphs.stream_lag.ChainLagSmoother, "incremental" / "batch": gtsam's fixed-lag smoothers), with
    the iSAM2 settings below."""
    from imugraph.graphs.stream_lag import ChainLagSmoother, keyframe_group

    params = gtsam.ISAM2Params()
    if options.factorization not in ("QR", "CHOLESKY"):
        raise SessionError("stream", "factorization", repr(options.factorization), '"QR" or "CHOLESKY"')
    params.setFactorization(options.factorization)        # QR: see StreamOptions.factorization
    params.setRelinearizeThreshold(isam2_thresholds(options.relinearize_threshold))
    params.relinearizeSkip = 1
    # check only the variables the update touches (and their ancestors) for relinearisation: the full
    # check computes the whole delta, O(K) per update (measured: 10 ms at 100 keyframes → 0.4 ms)
    params.enablePartialRelinearizationCheck = True
    if options.lag_s is None:
        return gtsam.ISAM2(params)
    lag = float(options.lag_s)
    if options.fixed_lag_solver == "chain":
        return ChainLagSmoother(lag, params, keyframe_group, options.lag_hold_s, deferred=True)   # see StreamSmoother._between_keyframes
    if options.fixed_lag_solver == "incremental":
        return gtsam.IncrementalFixedLagSmoother(lag, params)
    return gtsam.BatchFixedLagSmoother(lag)


def isam2_thresholds(rot_threshold: float) -> "gtsam.ISAM2ThresholdMap":
    """Per-type relinearisation thresholds: rotations (and gyro bias, rad/s ÷ 10) at `rot_threshold`;
    positions never by themselves (they carry no information, see cpp_velocity, and drift freely). One
    threshold for all re-linearised ~all variables at every update (positions move).

    Velocities at 0.5 m/s and gravity at 0.1 m/s²: the velocity rows are linear in both (v_{k+1} − v_k −
    g Δt − R_k Δv_k), only the rotation Jacobian's small gravity/velocity term depends on their linearisation
    point, but the whole velocity chain shifts together as new data move its bounded-velocity level, and at
    0.05 m/s / 0.01 m/s² that re-linearised every keyframe at once every few seconds (measured, BROAD 01 first
    120 s, iSAM2: 57 of 1477 updates re-linearised > 1600 variables, 100–180 ms each; p99 78 → 13 ms, filtered
    2.198° → 2.199°, smoothed 1.793° → 1.792°)."""
    m = gtsam.ISAM2ThresholdMap()
    m.insert(("x", np.r_[np.full(3, rot_threshold), np.full(3, 1e3)]))
    m.insert(("v", np.full(3, 0.5)))
    m.insert(("b", np.r_[np.full(3, 1e-3), np.full(3, rot_threshold / 10)]))
    m.insert(("g", np.full(3, 0.1)))
    m.insert(("f", np.full(3, 0.05)))      # field perturbation d_k (unit-field units; σ_d 0.003–0.015)
    m.insert(("c", np.full(13, 1e9)))      # θ (stream_calstate): its factors are linear containers, never relinearised
    m.insert(("w", np.full(3, 1e9)))       # window offsets Δo_w (stream_offsets): linear containers and a linear prior
    m.insert(("p", np.full(3, 1e9)))       # bounded position p_k (stream_position): linear containers and a linear prior
    return m


def velocity_process(options: StreamOptions, cal) -> tuple[float, float]:
    """σ_v (m/s), τ_v (s) of the stream's bounded-velocity factors: the options' where set, else the calibration's
    estimate (`Calibration.velocity_sigma/tau`), else the nominal process (`Calibration.velocity_process`, as `smooth_fixed`)."""
    sigma, tau = cal.velocity_process(options.velocity_sigma, options.velocity_tau)
    for name, x in (("velocity_sigma", sigma), ("velocity_tau", tau)):
        if not (np.isfinite(x) and x > 0):
            raise SessionError("stream", name, repr(x), "a positive number")
    return float(sigma), float(tau)


def acc_lead(options: StreamOptions, cal) -> tuple[int, float]:
    """δ = n + f (whole samples n ≥ 0, fraction 0 ≤ f < 1) of the accelerometer timing (calibration/acc_timing.py):
    the options' where set, else the calibration's `acc_lead_samples` (as `smooth_fixed`).

    Raises:
        SessionError: δ < 0 or not finite — row j would need the accelerometer of a later sample, which a
        causal stream does not have when row j's interval closes."""
    lead = float(options.acc_lead_samples if options.acc_lead_samples is not None else cal.acc_lead_samples)
    if not (np.isfinite(lead) and 0.0 <= lead <= 1e4):
        raise SessionError("stream", "acc_lead_samples", repr(lead),
                           "a finite δ ≥ 0 samples (a causal stream cannot use a later accelerometer sample)")
    whole = int(np.floor(lead))
    return whole, lead - whole
