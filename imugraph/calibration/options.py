"""Settings of the maximum-likelihood calibration and smoothing graphs (imugraph.calibration.ml).

Each field's comment records what it models and, where a variant was tried on the BROAD trials, what it
measured (so the defaults carry their evidence).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from imugraph.factors.robust import Kernel
from imugraph.graphs.solver import SolverParams


@dataclass
class Options:
    """Settings of the calibration and smoothing graphs.

    keyframe_hz: keyframe rate (one orientation state per rate/keyframe_hz samples; every sample is used).
    acc_kernel / mag_kernel: per-sample robust kernels (whitened units).
    """

    keyframe_hz: float = 5.0
    max_outer: int = 8
    noise_tol: float = 0.02
    reestimate_noise: bool = True
    acc_kernel: Kernel = field(default_factory=lambda: Kernel("huber", 2.0))
    mag_kernel: Kernel = field(default_factory=lambda: Kernel("huber", 2.0))
    solver: SolverParams = field(default_factory=lambda: SolverParams(max_iterations=30, relative_tol=1e-7))
    bias_prior_sigma: float = 0.05
    bias_segment_s: float = 5.0       # gyro bias: one value per segment, joined by a random walk
    bias_rw: float = 2e-4             # bias random-walk density, rad/s/√s (MEMS bias instability)
    estimate_bias_rw: bool = False    # q = bias_rw re-estimated per ML round by EM from the smoothed segment
    #   biases and their posterior covariances (calibration/bias_process.py; start: bias_rw; held in RW_BOUNDS).
    #   Off (H7, benchmarks/h7_bias_process.py, all 17): the ML q spans ≈ 5e-6 (04, 07, 24) to 1.4e-3 (21) — it
    #   follows unmodelled gyro errors more than a sensor property; mean 0.666° → 0.661° (04 −0.069°, 10 −0.059°,
    #   15 −0.015°, 16 −0.014°) but 36 +0.061° (then behind offline VQF), 07 +0.027°, 06 +0.018°, 02 +0.006°;
    #   +0.4–3 s CPU per trial. Fixed q instead (broad_published.py --opt bias_rw=…, 8 trials): 15/16 best at 5e-5
    #   (0.840°/0.382°) but 06 0.638°, 04 0.509°; 06 best at 5e-4 (0.552°); 02 best at today's 2e-4 (0.473°);
    #   bias_segment_s 2 or 10: every trial within 0.004°
    gyro_rate_error: float = 0.01     # κ: gyro error growing with rate (scale factor, misalignment)
    estimate_gyro_rate_error: bool = False  # κ re-estimated per ML round from the gyro factors' residuals and
    #   posterior covariances (calibration/gyro_rate.py; start: gyro_rate_error). Off: on BROAD the ML κ is
    #   ≈ 0.01 on 06 but 0.03 on 02 and runs to its 0.1 ceiling on 36 (1.32 → 2.23°); with correlated_noise
    #   17-trial mean 0.680° → 0.71° (04 +0.18°, 21 +0.23°). Fixed κ = 0.002 instead of 0.01: mean 0.712° →
    #   0.697°, but 30 0.83 → 1.05° (benchmarks/broad_published.py --opt gyro_rate_error=0.002)
    progress: bool = False
    max_corr_s: float = 0.5           # cap on the residual correlation time used for σ inflation
    correlated_noise: bool = False    # inflate σ by √τ (integrated autocorrelation time of residuals)
    #   True: BROAD 17-trial mean 0.712° → 0.680°, 36 1.32 → 0.94°, 32 −0.07°, 34 −0.06°, 16 −0.05°, 28 +0.03°,
    #   others within 0.01°; only the magnetometer is inflated (the accelerometer is in the velocity chain),
    #   and only where the first round's field residuals are correlated (02: τ = 1; 32/34/36: τ of 330–1230
    #   thinned samples, before the windows are fitted), where the cap max_corr_s binds (36: 0.25 s 0.86°,
    #   0.5 s 0.94°, 1 s 1.11°)  (C2, benchmarks/c2_noise_trace.py)
    linear_acceleration: str = "velocity"   # "velocity": keyframe velocities with a bounded-velocity
    #                                         prior (imugraph.factors.velocity); "noise": per-sample gravity factor
    velocity_sigma: float = 0.5       # σ_v, m/s: stationary std of the sensor's velocity (start value)
    velocity_tau: float = 2.0         # τ_v, s: its correlation time
    estimate_velocity_process: str = "bounded_ar2"   # "off", "free"/"bounded"[+"_hv"], "free_ar2"/"bounded_ar2"
    #   (default, below): σ_v, τ_v by an EM step per ML round from the smoothed velocities (calibration/velocity_process.py; start: the two above; "bounded":
    #   σ_v ≥, τ_v ≤ them — the settings are a floor on how much the sensor may move; "_hv": horizontal and
    #   vertical processes apart). Free estimates match the optical velocities on the translation trials
    #   (σ_v within ~5 %, τ_v ~10 %) but follow unmodelled accelerometer errors on rotation-only trials.
    #   BROAD 17-trial mean (acc_lead_samples 0) 0.768° → "bounded" 0.763° (16 −0.10°, 21 +0.06°; "bounded_hv"
    #   the same), "free" 0.774° (32 −0.31°, 04 +0.56°), "free_hv" 0.826° (01 +0.80°); with acc_lead_samples 1:
    #   0.724° → 0.690° "bounded", no trial worse: benchmarks/v1_velocity_process.py
    #   "free_ar2"/"bounded_ar2": a second-order (AR(2)) process instead, for a hand moving back and forth
    #   (calibration/velocity_ar2.py; its estimates match the optical AR(2) fit on 04, 07, 16). 17-trial mean
    #   0.712° → "free_ar2" 0.667° (32 −0.41°, 36 −0.11°, 01/02/04 −0.08°; 07 +0.09°; 15/16 +0.01°), "bounded_ar2"
    #   0.683° (32 −0.36°, 36 −0.11°; 07 +0.02°; the default: 36 ahead of offline VQF, no trial worse by more
    #   than 0.03°): benchmarks/broad_published.py --opt, benchmarks/v2_velocity_ar2.py
    #   H4, current model, per trial (benchmarks/h4_decompose.py TRIALS --tag free --opt
    #   estimate_velocity_process="'free_ar2'"): 17-trial mean 0.666° → 0.650°; 02 0.473 → 0.391° (its slow tilt
    #   0.200 → 0.136°, offline VQF 0.138°: the floor binds there, σ_v 0.50 m/s and τ_v 2 s against the ML 0.043 m/s
    #   and 0.40 s, smoothed |v| 0.18 m/s RMS on y; and its Ê, which absorbed that freedom, no longer settles:
    #   the settling gate drops it), 01 0.767 → 0.679°, 04 0.563 → 0.487° (Ê diagonals of 01/04 closer: 0.17/0.13/
    #   0.40 and 0.19/0.33/0.31 %), 32 0.476 → 0.420°; worse: 07 0.506 → 0.574°; the other 11 within 0.02°
    acc_rate_error: float = 0.01      # κ_a: accelerometer error growing with the specific force
    #   (H4, evidence only: 0.03 removes the slow-tilt excess over offline VQF where the motion is vigorous —
    #   06 slow tilt 0.220 → 0.107° (VQF 0.104°), 16 0.091 → 0.081° — but 06's heading pays: 0.557 → 0.587° total;
    #   16 0.401 → 0.359°, 15 0.879 → 0.869°, 02/07 within 0.003°; benchmarks/h4_error_split.py)
    estimate_acc_rate_error: bool = False  # κ_a re-estimated per ML round by maximising the marginal likelihood of
    #   the velocity increments (Kalman filter over the velocity chain, calibration/acc_rate.py), held in
    #   [acc_rate_error, 0.1]: the setting is a floor. Off (H6, benchmarks/h6_acc_rate.py, broad_published.py --opt):
    #   ML κ_a 0.082 on 01 (0.767 → 0.780°), 0.039 on 06 (0.557 → 0.583°: tilt 0.345 → 0.284°, heading 0.437 →
    #   0.509°), 0.016–0.020 on 04/07/32 (±0.003°), at the floor on 02/15/16 (ML 0.000/0.007/0.000: 16's slow
    #   tilt is not a κ_a|f| error by this likelihood; the AR(2) process takes the vigorous motion). Cost ≈ 0.3 s
    #   CPU per round on a BROAD trial
    position_sigma: float | None = None   # σ_p, m: keyframe positions integrating the velocities with a bounded
    #   (stationary Gauss–Markov) prior, the sensor stays within reach (graphs/velocity_block.py (P1)); None: off.
    #   Why (H11, benchmarks/h11_slow_drift.py): on BROAD 02/06 the smoothed velocities integrate to 4.9/18.6 m of
    #   travel (optical 0.56/0.46 m); the slow tilt about north is that phantom velocity (ė_v,y = −g ε_x, corr 0.90/0.82)
    #   and the magnetometer turns it into heading (ψ ≈ −tan δ ε_x, tan δ ≈ 2.7). BROAD, all 17 (h11_position.py
    #   --variant "position_sigma=1.0" ...): mean 0.647° → 0.639°, inclination 02 0.293 → 0.249°, 06 0.345 → 0.286°,
    #   but 06 0.557 → 0.591°, 07 0.506 → 0.550° (heading: the field's slow y deviation then goes to ψ); with
    #   field_sigma=(0.015, 0.006, 0.015): 0.606°, behind offline VQF only 02 (0.370 vs 0.366°), 16 (0.377 vs
    #   0.370°), 32 +0.017° (docs/results_issue2.md, session 16). Off: the σ_y setting was chosen on BROAD
    position_tau: float = 30.0        # τ_p, s: the position prior's correlation time
    estimate_position_sigma: bool = False  # σ_p re-estimated per ML round by EM from the smoothed positions and
    #   their posterior covariances (calibration/position_process.py (J1)), starting from position_sigma (1 m when
    #   None); position_em_inner EM steps per round at the round's orientations. Do not use (benchmarks/j2_travel.py:
    #   the held orientations hide the bent tilt; a simulated 220 m walk σ̂_p 0.44–0.51 m, 0.538 → 1.149°)
    position_em_inner: int = 1        # EM steps of σ_p per ML round at the round's orientations
    position_select: tuple | None = None  # candidate σ_p (m) for the final solve, 1e4 = "off": the one of largest
    #   Laplace marginal likelihood (calibration/position_select.py (J2)) at the ML rounds' converged noise; "off"
    #   winning gives the plain final solve. None: σ_p as position_sigma. (1e4, 1.0, 0.3, 0.1) with
    #   position_select_rounds (benchmarks/h11_position.py, j2_travel.py, docs/results_issue2.md session 17): BROAD
    #   0.647 → 0.632° (07 +0.072°: heading), with field_sigma=(0.015,0.006,0.015) 0.602°, 02/16 behind by 0.006°;
    #   "off" on simulated walks/drives and the gaittoolbox walk (= the defaults exactly); CPU 2.3–3.0 s
    position_select_field: tuple | None = None  # with position_select: candidate cross-field σ_d,y of the field
    #   perturbation, scored by (J2) (+ the field prior's normaliser) at the chosen σ_p; None: field_sigma as set
    position_select_rounds: bool = False  # with position_select: when a bound is chosen, the ML rounds run again
    #   with it (noise levels, bias, windows re-estimated under the bound) before the final solve
    position_select_field_rounds: bool = False  # with position_select_rounds and position_select_field: when a
    #   bound is chosen, the cross-field σ_d,y is chosen by (J2) AFTER ML rounds run under the bound at each
    #   candidate σ_d,y (its dof charge in the Σm re-estimate, ml.py), sequentially from field_sigma's σ_y upward,
    #   stopping when the evidence drops; "off" keeps field_sigma (task J2, docs/results_issue2.md). BROAD 17
    #   (h11_position.py): σ_y 0.003 kept on 10 of 12 bounded trials (0.006 worse by 4–38 nats), 0.006 on 34/36;
    #   0.622°, 4 behind offline VQF, 07 +0.072°: the evidence does not support the looser σ_y of the field pair
    position_select_stop: bool = False  # with position_select: candidates solved in the given order (loosest
    #   first), stopping at the first whose evidence is below the previous one's (unimodal ln Z(σ_p)): CPU (the
    #   candidates' common gyro preintegration is computed once in every run since session 17's final read, ml.py).
    #   Do not use: BROAD 01's ln Z is not unimodal (off > 1 > 0.3 < 0.1 m), the stop picks off instead of 0.1 m
    position_select_thin: int = 1  # with position_select_rounds: the candidates' magnetometer thinned by this
    #   further factor: CPU.
    #   2 or 4 on BROAD 01/02/24: choices kept, but LM 1–2 → 3 iterations per candidate, no CPU gain
    position_select_max_iter: int | None = None  # with position_select_rounds: the candidates' LM iterations
    #   capped (None: the rounds' solver): CPU. 1 on BROAD 17:
    #   every σ_p/σ_y choice unchanged, ln Z within 2.5 nats, errors within 0.001°, CPU 1.76–2.88 → 1.56–2.55 s
    gap_model: bool = True            # steps over 1.5 T are missing time (factors/gaps.py: variance G1, a keyframe
    #   at gaps > 50 ms, the per-sample blend and start values restart there); False: trusted like measured time
    #   (before session 16; e.g. for a clock whose jitter is not missing data)
    zero_velocity_at_rest: bool = False  # v = 0 ± 0.02 m/s at detected rest: BROAD 04 1.79 → 0.92°,
    #                                      but 01 1.59 → 1.99°, 30 1.11 → 2.01° (acc errors then tilt)
    acc_bias: bool = False            # a slowly varying accelerometer bias in the velocity state: off,
    #                                   on BROAD it absorbed the linear acceleration of the translation trials
    compensate_mag_delay: bool = True # pair each field sample with the orientation when it was sensed
    acc_lead_samples: float | None = None  # δ: accelerometer row j paired with the strapdown orientation of row
    #   j + δ (calibration/acc_timing.py; None: the session's own timing (acc_timing.session_lead: a simulator
    #   that holds ω over [t_j, t_{j+1}) records 0), else ½: instantaneous samples under the forward rule —
    #   from first principles, not fitted; 1: VQF's gyro-then-acc order; 0: rows as recorded). BROAD 17-trial
    #   mean 0.768° (0) → 0.736° (½) / 0.724° (1): 28 1.27 → 0.97 / 0.78°, 30 1.06 → 0.92 / 0.85°, 21 1.10 →
    #   1.05 / 1.08° (one-way spins about a horizontal axis); largest loss 04 +0.02 / +0.04°.
    #   Not estimated: in the graph δ trades with the tilt about the spin axis (benchmarks/c1_timing.py)
    disturbance_windows: bool = True  # windowed hard-iron offsets (imugraph.calibration.disturbance)
    noise_skip_excluded: bool = False  # the ML rounds' noise re-estimate sees only the field samples the solve
    #   sees: rows of weight 0 (unexplained disturbance windows) are left out of Σm (calibration/rounds.py).
    #   Off, their raw residuals leak into σ_mag (BROAD 32: the magnet's 58 µT → σ_z 0.7 → 6.6–8.8 µT), the
    #   window's "explained" test (≤ 3 σ_mag) flips, and the rounds cycle (period 5) to max_outer. On (BROAD, all
    #   17, broad_published.py --opt): 32 0.476 → 0.448° in 4 rounds (σ_mag 0.67 µT), but 36 1.211 → 1.287°
    #   (its σ_z 1.40 → 0.81 µT: the leak from its short unmodelled windows down-weighted a still-disturbed
    #   field), 34 +0.011°, 28 +0.008°; a simulated nav-frame disturbance: 7.45° (8 rounds) → 0.17°. Off
    freeze_window_decision: bool = False  # each disturbance window's "modelled" verdict (offset explains it:
    #   residual ≤ 3 σ_mag) is taken at its first fit and kept; its offset is still refitted every round
    #   (disturbance.fit_offsets keep_decision). The first fit sees orientations and σ_mag the window did not
    #   influence (it starts left out); re-judged each round, BROAD 32's verdict flipped with σ_mag (period 5).
    #   On (BROAD, all 17): 32 0.476 → 0.455°, converged in 6 rounds (σ_mag,z still leaks: 29.5 µT); the other
    #   16 identical (their verdicts never flip); simulated nav-frame disturbance 7.45° → 0.14°. Off: a
    #   simulated ATTACHED magnet (tests/test_disturbance.py, 3 × the field for 30 s) is then judged unexplained at
    #   its first fit and left out (0.30 → 0.39°; noise_skip_excluded alike): the ≤ 3 σ_mag test is passed there only
    #   thanks to the leak. Both need a verdict judged from a solve with the window modelled (not done)
    window_trial_verdict: bool = True   # each disturbance window's verdict judged on a solve WITH it modelled,
    #   once: a window whose offset reduces its residual is modelled for one round ("on trial"), then kept
    #   modelled for good if its residual RMS ≤ 3 × the undisturbed samples' residual RMS of that same solve
    #   (not σ_mag), else left out for good (disturbance.fit_offsets_on_trial, rounds.fit_windows). BROAD (all 17):
    #   only 32 0.476 → 0.420°, 34 0.933 → 0.881°, 36 1.211 → 1.008°; a modelled window's left-out rows go to
    #   calibration.json (`left_out`). Gates (benchmarks/b_window_gates.py): EXPLAINED 2.5–3.5 and TRIAL_GAIN
    #   0.4–0.5 change no verdict; TRIAL_GAIN ≥ 0.55 puts 36's windows (gain 0.535–0.662) on trial, they pass
    #   (1.01–1.19 ≪ 3) and 36 returns to 1.10–1.21°, never worse than off; ends 32's cycling rounds (3.78 → 1.73 s
    #   CPU: benchmarks/speed.py 16,32,34,36 --repeat 3 --opt window_trial_verdict=True); smooth_fixed starts
    #   without borrowing a far keyframe's field in the gaps it leaves (orientation_init borrow_field=False: 36
    #   from 79° to 1.15°). Default since session 15. On a short recording whose rows outside the windows do not
    #   identify D (BROAD 34's first 67 s: spread 0.011 < 0.05) the windows keep the σ_mag verdict
    #   (rounds.identified_without_windows; before: D's singular values 76, 45, 4.7 and the stream on 34 24.27°)
    heading_only_orientation: bool = False  # final orientations with the field as heading only
    #                                        (graphs.heading_block): BROAD mean 1.13° vs 1.06° joint, off
    field_sigma: float | tuple | None = (0.015, 0.003, 0.015)  # σ_d per nav axis (x along the horizontal
    #   field, y across it, z up), unit field; None: no perturbation. Gauss–Markov nav-field perturbation
    #   (factors/field.py): the indoor field varies with position (BROAD 01: 0.5–0.9° per axis at 10 s).
    #   BROAD 17-trial mean 0.99° → 0.83° (10 → 7 trials behind offline VQF); worse on 16, 26, 32 (0.61 →
    #   0.84°). Across the field 0.003: looser lets heading follow the gyro (01: 0.015 on y → 3.60°)
    field_tau: float = 1.0            # τ_d, s: its correlation time (2 s: mean 0.839°)
    gyro_map: bool = True             # gyro scale/misalignment E estimated jointly (calibration/gyro_map.py)
    #   from the intervals where the accelerometer sees gravity only, behind a coverage gate and a settling
    #   gate (else the plain model's result). Ungated, E ran to +40 % on BROAD 16 (16.8°): it absorbed
    #   unmodelled linear acceleration. Gated: BROAD 17-trial mean 0.83° → 0.77° (01 1.23 → 0.755°,
    #   04 1.17 → 0.548°, 02 0.424 → 0.470°, others identical). Until the final solve was fixed (it kept
    #   the rounds' β_k/e keys, met an indeterminate system at every λ and returned the last round's
    #   thinned-field solution) these were 0.793° / 0.524° / 0.443°, mean also 0.77°.
    #   On by default (its cost: one more ML round where the gates pass, β_k/e keys in the rounds)
    gyro_map_select: bool = False     # where E passes its gates, keep it only if, estimated without a block's
    #   intervals, it carries the accelerometer's gravity direction across that block (gyro strapdown from the
    #   block's first to its last window) significantly better than E = 0 (calibration/gyro_map_select.py:
    #   K-fold over time blocks, paired z over the blocks ≥ gyro_map_select_z); else E = 0.
    #   Cost where E passes its gates: folds + 1 more calibrations; elsewhere none. Off (H4): it keeps a
    #   simulated 2 % E and drops a spurious one, but on BROAD drops E on 01, 02 and 04 alike (z −2.42, −2.26,
    #   −1.88): 02 0.473 → 0.423°, 01 0.77 → 1.232°, 04 0.56 → 1.173° — at 0.2–0.3 % the accelerometer
    #   cannot see E (01: +0.5 % on every axis moves its statistic by z −0.1) and E's gain there is heading
    gyro_map_select_block_s: float = 4.0   # held-out block length, s
    gyro_map_select_folds: int = 2
    gyro_map_select_window_s: float = 0.5  # gravity averaged over the first and last window_s of each block
    gyro_map_select_z: float = 2.0
    gyro_map_sigma: float = 0.02      # prior std of the entries of E
    gyro_map_acc_tol: float | None = 2.0   # m/s²: only keyframe intervals with | |b_acc| − g | below this
    #   inform E (calibration/gyro_map.clean_intervals; None: all intervals)
    gyro_map_final: bool = False      # False: the final (all-sample) solve keeps the rounds' Ê (freeing it there:
    #   BROAD 02 0.44 → 0.52°, 01 0.79 → 0.73°, 04 0.53 → 0.58°; the rounds set noise levels and E)
    gyro_map_tol: float = 3e-4        # E settled when no entry moves more than this in a round
    gyro_map_max_contraction: float = 0.5   # E kept only if each step ≤ this × the one before; the rounds
    #   stop at the first larger step and the plain model's rounds run (gyro_map_fallback)
    #   (BROAD 01/02/04: steps shrink 0.12–0.39 per round; 24: 0.52 then 0.67 per round, E off-diagonal
    #   to −0.8 %, 0.51 → 0.73° if kept; 06/07/16/21/30/32 with the coverage gate lowered: 0.62 to 6.9)
    gyro_map_fallback: str = "restart"  # when the settling gate fails: "restart" reruns the plain rounds from
    #   step 1's state (bit-identical to gyro_map=False); "warm" continues them from the E rounds' state with
    #   Ê = 0 (BROAD 24: 4.3 → 3.0 s CPU, orientations within 1.3e-4° of the plain model) — not the default:
    #   on a simulated 30 s attached magnet (tests/test_disturbance.py) the warm rounds, starting from the
    #   E rounds' inflated σ_mag, end with the window classified "not modelled", the plain model "modelled"
    gyro_map_min_turns: float = 15.0  # coverage gate: E estimated only with this many turns of rotation in
    #   those intervals (gyro_map.clean_turns), else left at 0 (info["gyro_map_gate"])
    round_min_samples: int = 8        # ML rounds see every n-th field sample, keeping at least this many
    #                                   per keyframe (the dof correction needs them); the final solve sees all
    round_relative_tol: float | None = 1e-4   # LM stopping tolerance of the ML rounds (None: solver's);
    #   the rounds only steer noise levels and bias (σ from Σr², which moves ~1e-4 × less than noise_tol)
    #   and warm-start the final solve (solver tolerance): BROAD 17-trial mean 0.9937° → 0.9917°, largest
    #   change 0.036° (trial 10, whose rounds never converge), LM iterations −30 % (trial 01: 23 → 15)
    weak_theta_fraction: float = 0.05   # when D, o are not identifiable (calibrate(allow_weak=True) on too little
    #   rotation: weak_initial, D = s·I, o = 0) their prior std is this fraction of the scale s (o: twice it).
    #   0.05 lets the translation trials move o by 4–5 µT (BROAD 16: o = (−4.2, 3.2, 0.3) µT, 10 % of |m|)
    #   along what the motion correlates with; 1e-4 holds D, o at the sphere (dip still free). BROAD (G4,
    #   benchmarks/broad_published.py 10,12,15,16 --opt weak_theta_fraction=1e-4): 16 0.58 → 0.47°, 15 0.95 →
    #   0.92°, 12 0.49 → 0.48°, but 10 0.34 → 0.42°; 0.01: no change (the data outweigh it). With weak_mag_delay
    #   (below) 1e-4 against 0.05: 10 0.327 → 0.413°, 12 0.450 → 0.473°, 15 0.879 → 0.832°, 16 0.401 → 0.425°. Off
    weak_mag_delay: bool = True       # the weak path (D, o not identifiable) also estimates the magnetometer's lag
    #   behind the gyro (calibration/initial.weak_initial; the identifiable path always does: 8.6–9.9 ms on BROAD);
    #   off, the weak path paired each field sample with the orientation ≈ 2.7 samples after it was sensed, and
    #   the field perturbation d_k absorbed that (its correlation time on 16: 0.2 s; with the lag: 0.6–1.5 s).
    #   BROAD (G4, benchmarks/broad_published.py --opt weak_mag_delay=True): lag 9.0–9.9 ms on 10/12/15/16;
    #   16 0.576 → 0.401°, 15 0.951 → 0.879°, 12 0.489 → 0.450°, 10 0.336 → 0.327°, the 13 identifiable trials
    #   unchanged (they never take this path); 17-trial mean 0.683° → 0.666°. Cost: ≈ 0.05–0.08 s CPU (16). On
    #   by default (the lag is the sensor's, not the calibration's: one model on both paths)
    # Tried and removed (G4): σ_d re-estimated per ML round by an EM step from the smoothed d_k — the estimates
    #   never settled (rounds ran to max_outer, 2–3× the time) and BROAD 04 went 0.563 → 1.176°. Fixed settings
    #   measured with weak_mag_delay (tuned on BROAD, so evidence only, not adopted): field_sigma=(0.015, 0.006,
    #   0.015): mean 0.637° (15 0.827°, 16 0.376°; 32 0.476 → 0.608°); field_tau=3.0: mean 0.650° (32 → 0.566°).
    field_select: bool = False        # σ_d, τ_d (and nothing else) chosen per recording among a small grid
    #   (calibration/field_select.DEFAULT_CANDIDATES: these settings, σ_y ×2, τ_d ×3, both) by K-fold held-out
    #   prediction of the magnetometer (blocks of field_select_block_s held out in turn; the smoother without
    #   them predicts them); the truth is not used. Cost: candidates × folds + 1 calibrations (≈ 9×: 20–86 s
    #   CPU per BROAD trial). BROAD (G5, benchmarks/g5_field_select.py, all 17): mean 0.666° → 0.648°, behind
    #   offline VQF 4 → 2 trials (02 0.473 → 0.488°, 16 0.401 → 0.379° vs 0.370°; 15 0.879 → 0.821°, 06 0.557 →
    #   0.526° now ahead); τ_d ×3 or σ_y ×2 & τ_d ×3 chosen on 16 of 17, each with paired z 2.4–11.1. Worse:
    #   32 0.476 → 0.608° (σ_y ×2 chosen, scores 0.03 % apart yet z 2.55: its held-out error is mostly the
    #   clipped magnet samples), 26 +0.024°, 02/04 +0.015°, 34 +0.012°. The score keeps falling for τ_d ×10 (01,
    #   02, 16): the grid's edge decides τ_d. The same held-out score cannot judge the gyro map (02/01/04: map
    #   on vs off within 0.6 %, and on 04 it prefers off, 0.563 → 1.173°). Off (G5)
    field_select_block_s: float = 2.0  # length of the held-out blocks, s
    field_select_folds: int = 2        # folds (block b held out in fold b mod folds)
    field_select_z: float = 2.0        # the best candidate replaces these settings only when its held-out score
    #   is lower by ≥ this many standard errors, paired over the blocks (field_select.choose)
    velocity_prior_strength: float = 300.0  # ν_0 of estimate_velocity_process="map_ar2": the settings' process
    #   (velocity_sigma, velocity_tau) as an inverse-gamma prior on the AR(2) innovation variance q worth ν_0
    #   pseudo-innovations (calibration/velocity_ar2.py) instead of the hard floor of "bounded_ar2". H9, all 17
    #   (benchmarks/h9_velocity_trace.py --opt estimate_velocity_process="'map_ar2'" --opt velocity_prior_strength=300|3000): "map_ar2" at 300: mean 0.666° → 0.662° (02 0.473 → 0.438°, 01
    #   −0.025°, 04 −0.031°, 32 −0.050°; 07 0.506 → 0.563°, 26 +0.039°); at 3000: 02 0.563°, 07 0.507°. A BROAD trial
    #   holds 2–3 thousand innovations, so the prior blends ML and floor; no ν_0 frees 02 and keeps 07. Off
    velocity_em_inner: int = 1        # EM steps of an AR(2) velocity process per ML round at the round's
    #   orientations (E-step by a banded solve of the velocity chain, no graph solve: calibration/velocity_em.py);
    #   1 (default, as before): one step per round (the rounds' solves are the E-steps). 30 with "free_ar2" (H9, all 17;
    #   h9_velocity_trace.py --opt estimate_velocity_process="'free_ar2'" --opt velocity_em_inner=30): rounds
    #   02 7 → 5, 07 7 → 4, CPU mean 1.81 → 1.82 s (load ≈ 4), mean 0.650° → 0.652° (06 +0.037°). Off
