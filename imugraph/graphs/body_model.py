"""Options, joints and per-sensor set-up of the body estimator (imugraph.graphs.body).

Joints connect sensed segments only. A sensed child C whose nearest sensed ancestor P is not its parent
(unsensed links between, e.g. L5, L3, T12 between Pelvis and T8; Neck between T8 and Head) gets one lumped
joint at C's origin; its parent-side position is the chain's summed neutral-pose offsets (in the neutral
pose every segment frame is world-aligned, so offsets add). Lumped joints are softer (the chain bends).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imugraph.body.placement import nominal_placement
from imugraph.calibration.rest import MIN_REST, detect_rest, noise_from_rest
from imugraph.errors import SessionError


@dataclass(frozen=True)
class BodyOptions:
    """Settings of the body estimator (defaults chosen by measurement, see imugraph.graphs.body).

    Attributes:
        keyframe_every: one state per this many samples; IMU preintegrated between keyframes.
        joint_sigma_m: joint (B2) noise, m; None = hard (noiseModel.Constrained).
        lumped_joint_sigma_m: joint noise of lumped joints (unsensed links between), m.
        lever_sigma_m: prior σ of the lever arms around the nominal placement (B3), m; None: no prior
            (ablation: the sensor-to-segment position factors dropped).
        use_joints: False drops the joint factors (B2) and lever arms (ablation: independent sensors).
        gyro_noise, acc_noise: per-sample noise σ (rad/s, m/s²); None: from the N-pose rest (floored).
        integration_sigma: preintegration's position-integration noise density (gtsam integrationCovariance
            = σ² I): the discrete model p+ = p + v dt + ½ a dt² misses O(jerk dt³) terms on fast limbs.
        gyro_bias_sigma, acc_bias_sigma: bias prior σ around the N-pose estimate (gyro: mean rate at rest;
            acc: 0). 0.002 rad/s (≈ 0.1 °/s, run-to-N-pose change of a MEMS gyro): with 0.02 the biases
            absorbed model errors (estimates 0.01 rad/s off while the N-pose mean was within 0.001) and the
            relative headings of little-moving segments drifted — walk, no magnetometer: worst joint 4.53° →
            0.92°; CMU 131_01: 5.71° → 2.69° (seed 7), 2.80° → 2.85° (seed 3).
        bias_rw, acc_bias_rw: bias random walk densities (gyro rad/s/√s, acc m/s²/√s): one bias per sensor per
            `bias_segment_s` joined by BetweenFactorConstantBias, σ = rw·√Δt (b_{m+1} − b_m ~ N(0, rw² Δt));
            bias_rw None: one constant bias per sensor. Default 1e-3 rad/s/√s (≈ 0.06 °/s after 1 s, 0.4 °/s
            after a minute: the upper end of consumer MEMS gyro drift incl. warm-up/temperature) and 2e-3
            m/s²/√s; measured in imugraph.graphs.body's docstring.
        bias_segment_s: duration of one bias segment, s.
        root_heading_sigma_rad: gauge: heading prior of the root sensor at k = 0.
        heading_sigma_rad: weak heading prior of every other sensor at k = 0 (None: none).
        tilt_sigma_rad: tilt prior σ at k = 0 (weak: the accelerometers see tilt).
        start_velocity_sigma: velocity prior at k = 0 (the N-pose is static), m/s.
        npose: (t_start, t_end) of the static N-pose in s; None: detected by rest detection at the start.
        npose_heading_deg: forward heading in the N-pose when the hips cannot tell it (no hip joints).
        placements: nominal {segment: (bRs (3,3), b_pos (3,))}; segments missing here get
            `imugraph.body.placement.nominal_placement` (on the skin mid-segment, z out of the skin, x along
            the segment; `default_placement`).
        init: "nominal": sensors missing from `placements` start at their nominal placement; "motion"
            (helper Q22b): their headings about the vertical from the joint accelerations after the N-pose
            (imugraph.body.placement_motion (H1)–(H4); every build_problem, so also the fixed lag's bootstrap);
            "auto" (default since session 22): "motion" only for the sensors whose motion placement is >
            init_motion_switch_deg from nominal (real qmt full body: all 15 non-root sensors 158–180° off, LM 30 + 30
            at the cap → 7 + 2; 4a simulations identical to "nominal" on seeds 0–9; docs/results_issue4.md "Q22b").
        init_motion_window_s: with init "motion"/"auto", the seconds after the N-pose whose samples (H3) uses.
        use_mag: magnetometer factors (B5) with a per-sensor field direction from the N-pose.
        mag_sigma: σ of the normalised field direction (unitless, per axis); with mag_sigma_ml its floor.
        mag_sigma_ml: how many times each sensor's field-direction σ is estimated by maximum likelihood
            (body.mag_noise, B5'): first at a magnetometer-free solution, then again at the solution with them
            (one more pass if some σ moved by > 10 %); 0: mag_sigma for all, one pass. With a bootstrap the
            fixed lag takes them from the bootstrap's batch.
        init_heading_from_mag: initial sensor headings from the magnetometers (no magnetometer factors);
            None: when use_mag, or when every sensor has magnetometer samples in the N-pose.
        hinges: segments (children) whose joint is a hinge about the lateral axis (B4), e.g. ("RightLowerLeg",).
        hinge_sigma_rad: σ of the hinge residual.
        g: gravity, m/s².
        max_iterations, relative_tol: LM stopping.
        ordering: "colamd" or "metis".
        max_keyframe_turn_rad: extra keyframes so that no sensor turns more than this between two
            (Σ|ω|dt; None: regular keyframes only). 2.5 rad < π, the limit of gtsam's preintegrated
            rotation; at 60 Hz and keyframes every 6 samples it acts above ≈ 25 rad/s only (fast hands).
        axial_segments: segments whose sensor may turn about the segment's long axis over time (soft-tissue
            artefact; imugraph.factors.body_axial (S1)–(S3)); only seen through `hinges` touching them. () =
            rigid sensors (today's behaviour).
        axial_sigma_rad: σ of that turn (S2); None: `STA_AXIAL_SIGMA_RAD` by segment kind (literature).
        axial_tau_s: correlation time τ of (S2), s. 0.1 s: the artefact has the frequency content of the
            movement itself (Leardini et al., Gait Posture 21 (2005) 212, review), here a stride of 1.4 s
            with harmonics to ≈ 2.5 Hz; a first-order process with τ = 0.1 s is flat to 1/(2πτ) ≈ 1.6 Hz.
        axial_offset_sigma_rad: weak prior σ of the constant axial offset c (S1): the N-pose says nothing
            about each leg's axial rotation in the stance (e.g. toes turned out), 0.17 rad ≈ 10°.
        axial_hinge_sigmas_rad: σ of the two components (x̂, ẑ of the parent segment) of the hinge (S3):
            at small flexion the internal/external rotation and the ab/adduction of the joint. Knee in
            walking, biplane radiography of 39 knees on a treadmill (PMC7477710): range of motion IE 11.5°,
            AbAd 3.7°; a sinusoid of peak-to-peak r has σ = r/(2√2): 4.1° → 0.07 rad, 1.3° → 0.023 rad.
        knee_gain_segments: thighs whose sensor turns about the long axis by c_k + g·κ_k, κ the knee flexion
            (imugraph.factors.knee_sta (G1)–(G3), one gain g per thigh estimated by the graph), seen through the
            knee hinge: the knee (the thigh's child) must be in `hinges`; () = rigid sensors (today's behaviour).
        knee_gain_sigma: prior σ of g (G2), rad/rad.
        knee_gain_offset_tau_s: correlation time τ_c of the offset c_k (G2), s; None: one constant offset.
        knee_gain_offset_sigma_rad: σ_c of the offset (G2).
        knee_gain_hinge_sigmas_rad: σ of the hinge (S3) of such a knee; None: axial_hinge_sigmas_rad.
        knee_gain_mode: "graph" (c_k, g unknowns of the hinge pass, with the poses) or "two-stage" (no hinge pass:
            c_k, g by least squares (G4) on the output's knees, the poses held fixed).
        knee_gain_apply: "offset+gain" (the output thigh turned by c + g κ) or "gain" (by g κ only).
        knee_gain_screw_home: "two-stage" only: the knee's own internal rotation per flexion (rad/rad, G5) that
            the hinge-implied turn is first reduced by; 0: a pure hinge.
        knee_gain_turn: "two-stage" only: "hinge" (the turn the hinge (S3) asks for) or "cardan" (minus the part the
            knee's own flexion × ab/adduction explains, G6).
        unsensed_sigma_rad: unsensed links between two sensed segments (neck, lumbar spine) as estimated
            segments, the relative rotation shared among the chain's joints with this σ per joint
            (imugraph.graphs.body_chain (C1)–(C4), a second batch pass); None: lumped joints and the ties (K2).
        chain_offset_sigma_m: prior σ of the segment offsets along such a chain (C2, C3), m.
        unsensed_prior: "shared" (C4: between the neighbours and the links, pulls the sensed segments too) or
            "fixed" (C4': a prior on each link towards the first pass's ties, the sensed segments untouched).
        unsensed_chains: the distal sensed segments (e.g. ("Head",): the neck) whose unsensed chain is modelled;
            (): all chains between two sensed segments.
        unsensed_npose_sigma_rad: with unsensed_prior "fixed", σ of (C4') at the N-pose keyframes (C5: there every
            segment is aligned, which pins the constant part of a link's rotation that no sensor sees); None: σ.
        unsensed_sigma_gain: with "fixed", σ of (C4') grows with the chain's bend θ_k between its sensed ends
            (first pass): σ_k = unsensed_sigma_rad + gain·θ_k (C6: a straight chain stays on the tie, a bent one
            may share its bend differently); None: constant σ.
        lever_prior_frame: "nominal" (the lever priors (B3) in the sensor frame of the nominal placement
            rotation) or "estimated" (a second LM pass, warm-started, with each lever prior's mean turned into the
            sensor frame of the N-pose estimate bRs: imugraph.graphs.body_neck (N6); batch only); "lumped": the
            same for the levers of the lumped joints only.
        lever_pass_lumped_sigma_m: σ of the lumped joints in that second pass (None: lumped_joint_sigma_m).
        lever_pass_iterations: LM iterations of that second pass (None: max_iterations).
        unsensed_bend: distal sensed segments (e.g. ("Head",): the neck) whose single unsensed link the output
            turns with its upper neighbour A by the constant bend the solved lumped joint's levers imply
            (body_neck (N5)) instead of the ties (K2); (): the ties for all.
        unsensed_bend_length_sigma_m: σ of (N7), imugraph.graphs.body_neck: in the (N6) pass, for each lumped joint of
            `unsensed_bend`, the graph's distal point must lie the skeleton's |o_D| from the link's base (a rigid link
            of known length, the constant bend its only freedom); None: no such factor (today's behaviour).
        lever_pass_bend_sigma_m: σ of the lumped joints of `unsensed_bend` (the neck) in the (N6) pass only, the other
            lumped joints (the lumbar spine) keep theirs (body_neck (N8)); None: lumped_joint_sigma_m. Default 5 mm since session 21
            (chosen on seeds 0–4, checked on held-out seeds 5–9: docs/results_issue4.md).
        unsensed_bend_mag_free: with use_mag, (N5) reads the bend from the (N6) graph solved once more without the
            magnetometer factors (body_neck (N9)); the orientations stay the magnetometer solution's. Default True since session 21.
        lag_neck_from_bootstrap: solve_body_incremental with a bootstrap: the (N6) pass ((N8), (N9) as set) runs on the
            bootstrap's batch graph and the streamed output turns `unsensed_bend`'s links by the constant bend (N5) read
            there (body_neck.bootstrap_bend); False: the neck keeps the ties (K2) there (single_pass_options).
        lag_neck_stream: solve_body_incremental with a bootstrap (helper L22, imugraph.graphs.body_lag_neck): the
            bootstrap's (N6) pass ((N8), (N9) as set) gives the anchor of the stream's levers, the stream keeps the
            neck's lumped joint at lever_pass_bend_sigma_m (N8), and each keyframe's output turns the neck by the bend
            (N5) of the stream's levers when it leaves the window (filtered: right after its update). False: ties.
        lag_neck_anchor_sigma_m: with lag_neck_stream, σ of the anchor prior on the neck's lumped-joint levers (L2)
            (None: the 5 mm of every lever anchor).
        lag_bootstrap_overlap_s: solve_body_incremental with a bootstrap (helper L22): the bootstrap's keyframes of its
            last this many seconds are solved again by the stream (anchored before them, started at the bootstrap's
            estimate), so they are smoothed with the data that follow; 0: output as the bootstrap left them.
        lag_bootstrap_scale: the auto bootstrap (imugraph.graphs.body_bootstrap (A1)) ends once every sensor has turned
            ≥ scale × 1 rad and accelerated ≥ scale × 2 m/s beyond the N-pose (helper L22: the placements bRs the stream
            holds come from it; CMU 131_02's shoulder needs more motion than 1×).
        lag_bootstrap_marginal: the fixed lag (helper L22, (L7)): instead of diagonal anchor priors at the bootstrap's
            last keyframe, the bootstrap's own factors enter the smoother as its first update (started at the bootstrap's
            estimate, so their linearisation is good) and the smoother marginalises them; the last N-pose keyframes stay
            in the window, and the placements bRs, ψ are re-estimated from them at every update. False: anchors.
        lag_bootstrap_settle_deg, lag_bootstrap_settle_step_s: the auto bootstrap, after (A1), is solved again
            every step s longer until no sensor's bRs moves by settle_deg or more (imugraph.graphs.body_lag_settle (A2));
            None: (A1) alone.
        lag_neck_mag_offset: with lag_neck_stream, use_mag and unsensed_bend_mag_free: the stream's bend (L4) is read
            from its levers plus the offset (N9)'s magnetometer-free levers had from the bootstrap's own (body_lag_neck
            (L8)); False: the bootstrap's (N9) neck levers start the stream, the bend read from its levers as they are.
        lag_init_causal: solve_body_incremental (helper B23, body_lag_boot.causal_start (C1)): the stream's problem takes
            its N-pose and its init "motion"/"auto" placements from the rows of its bootstrap only (no bootstrap: the
            nominal start). Default since session 23 (bit-identical on the default lag path, which reads no placement before
            its bootstrap; (L7) / L22's options read up to 160° of future data without it). False: from the whole session
            (init_motion_window_s after the N-pose: rows not yet received).
    """

    keyframe_every: int = 6
    joint_sigma_m: float | None = 0.003
    lumped_joint_sigma_m: float = 0.02
    lever_sigma_m: float | None = 0.07
    use_joints: bool = True
    gyro_noise: float | None = None
    acc_noise: float | None = None
    integration_sigma: float = 1e-2
    gyro_bias_sigma: float = 0.002
    acc_bias_sigma: float = 0.2
    bias_rw: float | None = 1e-3
    acc_bias_rw: float = 2e-3
    bias_segment_s: float = 1.0
    root_heading_sigma_rad: float = 1e-3
    heading_sigma_rad: float | None = 1.0
    tilt_sigma_rad: float = 0.5
    start_velocity_sigma: float = 0.05
    npose: tuple | None = None
    npose_heading_deg: float = 0.0
    placements: dict = field(default_factory=dict)
    init: str = "auto"                                  # session 22 default; "nominal": before; "motion": every sensor (H1)–(H4)
    init_motion_window_s: float = 30.0                  # (H3) window after the N-pose, s
    init_motion_switch_deg: float = 45.0                # init "auto": motion placement only if this far from nominal
    use_mag: bool = False
    init_heading_from_mag: bool | None = None
    mag_sigma: float = 0.05
    mag_sigma_ml: int = 2
    hinges: tuple = ()
    hinge_sigma_rad: float = 0.05
    g: float = 9.81
    max_iterations: int = 30
    relative_tol: float = 1e-3
    ordering: str = "colamd"
    max_keyframe_turn_rad: float | None = 2.5
    axial_segments: tuple = ()
    axial_sigma_rad: float | None = None
    axial_tau_s: float = 0.1
    axial_offset_sigma_rad: float = 0.17
    axial_hinge_sigmas_rad: tuple = (0.07, 0.023)
    knee_gain_segments: tuple = ()
    knee_gain_sigma: float = 0.5
    knee_gain_offset_tau_s: float | None = 2.0
    knee_gain_offset_sigma_rad: float = 0.17
    knee_gain_hinge_sigmas_rad: tuple | None = None
    knee_gain_mode: str = "graph"
    knee_gain_apply: str = "offset+gain"
    knee_gain_screw_home: float = 0.0
    knee_gain_turn: str = "hinge"
    unsensed_sigma_rad: float | None = None
    chain_offset_sigma_m: float = 0.01
    unsensed_prior: str = "shared"
    unsensed_chains: tuple = ()
    unsensed_npose_sigma_rad: float | None = None
    unsensed_sigma_gain: float | None = None
    lever_prior_frame: str = "lumped"          # session 21 default (was "nominal"): (N6) for the lumped joints
    lever_pass_lumped_sigma_m: float | None = None
    lever_pass_iterations: int | None = None   # session 21: the (N6) pass to convergence (2–3 steps; (N8) needs it)
    unsensed_bend: tuple = ("Head",)           # session 21 default (was ()): the neck by (N5); single-pass solves keep (K2)
    unsensed_bend_length_sigma_m: float | None = None   # (N7) neck-length factor in the (N6) pass; None: none
    lever_pass_bend_sigma_m: float | None = 0.005       # (N8) σ of unsensed_bend's lumped joints in the (N6) pass (session 21 default; was None)
    unsensed_bend_mag_free: bool = True                 # (N9) the bend from the (N6) graph without magnetometers (session 21 default)
    lag_neck_from_bootstrap: bool = False               # fixed lag / iSAM2: (N5) with the bend of its bootstrap's (N6) pass; False: ties
    lag_neck_stream: bool = False                       # fixed lag / iSAM2 (helper L22): (N5) read from the stream's own levers (body_lag_neck)
    lag_neck_anchor_sigma_m: float | None = None        # (L2) σ of the neck levers' bootstrap anchor in the stream; None: 5 mm
    lag_bootstrap_overlap_s: float = 0.0                # (L5) the bootstrap's last seconds re-estimated by the stream; 0: none
    lag_bootstrap_scale: float = 1.0                    # (L6) the auto bootstrap's (A1) turn and Δv thresholds × this
    lag_bootstrap_marginal: bool = False                # (L7) the bootstrap's factors enter the fixed lag (N-pose kept): bRs keeps improving
    lag_bootstrap_settle_deg: float | None = None       # (A2) the auto bootstrap extended until its bRs change < this; None: (A1) only
    lag_bootstrap_settle_step_s: float = 1.0            # (A2) the step of that extension, s
    lag_neck_mag_offset: bool = False                   # (L8) with magnetometers: (L4) reads levers + the bootstrap's (N9) offset
    lag_init_causal: bool = True                        # (C1) fixed lag / iSAM2: init "motion"/"auto" and the N-pose from the bootstrap's rows only


# σ of the sensor's turn about the segment's long axis (soft-tissue artefact, rigid part), by segment-name
# suffix: fluoroscopy vs marker clusters in gait (6 TKA subjects, PMC8631460): largest rigid STA of the thigh
# cluster ≈ 10°, of the shank cluster ≈ 7° (in swing); read as the amplitude of a gait-locked oscillation,
# σ = amplitude/√2: 7.1° and 4.9°. Other segments (not measured there): the shank's value.
STA_AXIAL_SIGMA_RAD = {"UpperLeg": np.deg2rad(10.0) / np.sqrt(2.0), "LowerLeg": np.deg2rad(7.0) / np.sqrt(2.0)}


def axial_sigma(opts: BodyOptions, name: str) -> float:
    """σ of (S2) for segment `name`: opts.axial_sigma_rad, else `STA_AXIAL_SIGMA_RAD` by suffix."""
    if opts.axial_sigma_rad is not None:
        return float(opts.axial_sigma_rad)
    key = next((k for k in STA_AXIAL_SIGMA_RAD if name.endswith(k)), "LowerLeg")
    return float(STA_AXIAL_SIGMA_RAD[key])


@dataclass(frozen=True)
class BodyJoint:
    """A joint between two sensed segments: centre at the child's origin.

    b_parent: joint centre in the parent SEGMENT frame (summed offsets), m; b_child: in the child's (0).
    """
    name: str
    parent: str
    child: str
    b_parent: np.ndarray
    b_child: np.ndarray
    lumped: bool


def body_joints(skel) -> list[BodyJoint]:
    """Joints between sensed segments (topological order), lumping unsensed links (module docstring)."""
    sensed = set(skel.sensed)
    out = []
    for i, name in enumerate(skel.names):
        if name not in sensed or skel.parents[i] < 0:
            continue
        off = np.array(skel.offsets[i], float)
        p = skel.parents[i]
        lumped = False
        while p >= 0 and skel.names[p] not in sensed:
            off = off + np.asarray(skel.offsets[p], float)
            p = skel.parents[p]
            lumped = True
        if p < 0:
            raise SessionError("skeleton", f"sensed[{name}]", "no sensed ancestor", "a sensed root segment")
        out.append(BodyJoint(f"{skel.names[p]}-{name}", skel.names[p], name, off, np.zeros(3), lumped))
    return out


@dataclass
class SensorSetup:
    """Per-sensor quantities derived from the session before building the graph."""
    name: str
    sigma_gyr: np.ndarray
    sigma_acc: np.ndarray
    gyro_bias0: np.ndarray
    bRs_nom: np.ndarray
    b_pos_nom: np.ndarray


def npose_samples(session, opts: BodyOptions) -> tuple[np.ndarray, str]:
    """Indices of the static N-pose: opts.npose window, or the common rest run at the start of all sensors."""
    t = np.asarray(session.t, float)
    if opts.npose is not None:
        t0, t1 = opts.npose
        idx = np.flatnonzero((t >= t0) & (t <= t1))
        if idx.size == 0:
            raise SessionError(session.source, "npose", f"{opts.npose}", f"a window inside [{t[0]}, {t[-1]}] s")
        return idx, "given"
    rest = np.ones(t.size, bool)
    for s in session.sensors.values():
        rest &= detect_rest(s)
    # the first common rest run that starts within 0.5 s (window edges may flag the very first samples)
    start = np.flatnonzero(rest[: max(1, int(np.searchsorted(t, t[0] + 0.5)))])
    if start.size:
        i0 = int(start[0])
        i1 = i0 + (int(np.argmin(rest[i0:])) if not rest[i0:].all() else rest.size - i0)
        if i1 - i0 >= MIN_REST:
            return np.arange(i0, i1), "detected"
    return np.arange(min(t.size, MIN_REST)), "assumed"


def sensor_setup(session, skel, opts: BodyOptions, npose_idx: np.ndarray) -> dict[str, SensorSetup]:
    """Noise levels and gyro bias from the N-pose rest, nominal placements."""
    mask = np.zeros(session.t.size, bool)
    mask[npose_idx] = True
    out = {}
    for name in skel.sensed:
        if name not in session.sensors:
            raise SessionError(session.source, "sensors", f"no sensor for '{name}'", "one sensor per sensed segment")
        s = session.sensors[name]
        noise = noise_from_rest(s, mask)
        sg = np.full(3, opts.gyro_noise) if opts.gyro_noise is not None else np.maximum(noise["gyr"], 1e-3)
        sa = np.full(3, opts.acc_noise) if opts.acc_noise is not None else np.maximum(noise["acc"], 1e-2)
        bRs, b_pos = opts.placements[name] if name in opts.placements else default_placement(skel, name)
        out[name] = SensorSetup(name, sg, sa, np.asarray(noise["gyro_bias"], float), np.asarray(bRs, float),
                                np.asarray(b_pos, float))
    return out


def default_placement(skel, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(bRs, b_pos) assumed for a sensor without a given placement: the nominal site (imugraph.body.placement)."""
    p = nominal_placement(skel, name)
    return np.asarray(p.bRs, float), np.asarray(p.b_pos, float)


def keyframes(n: int, every: int, turn: np.ndarray | None = None, max_turn: float | None = None) -> np.ndarray:
    """Keyframe sample indices: every `every`-th sample, the last sample always included.

    With `turn` ((N,) rotation angle of each sample interval, rad, e.g. max over sensors of |ω − b̂| dt) and
    `max_turn`, a keyframe is also inserted before the interval's accumulated turn would exceed max_turn
    (gtsam's tangent-space preintegration holds Log(ΔR), |θ| < π; see factors.body.exact_rotation_gyro);
    the regular spacing restarts from there.
    """
    every = max(1, int(every))
    if turn is None or max_turn is None:
        kf = np.arange(0, n, every)
        return kf if kf[-1] == n - 1 else np.append(kf, n - 1)
    kf, a, acc = [0], 0, 0.0
    for i in range(n - 1):
        if i - a == every or (i > a and acc + turn[i] > max_turn):
            kf.append(i)
            a, acc = i, 0.0
        acc += float(turn[i])
    if kf[-1] != n - 1:
        kf.append(n - 1)
    return np.asarray(kf, int)


def bias_segments(kf_t: np.ndarray, segment_s: float | None) -> np.ndarray:
    """(K,) bias segment index of every keyframe: ⌊(t_k − t_0)/segment_s⌋ renumbered 0, 1, … (None: all 0).

    Keyframe k's ImuFactor to k+1 uses the bias of segment[k]; depends on keyframe times only, so a
    prefix of the session (incremental bootstrap) gets the same segments."""
    kf_t = np.asarray(kf_t, float)
    if segment_s is None or kf_t.size == 0:
        return np.zeros(kf_t.size, int)
    raw = np.floor((kf_t - kf_t[0]) / float(segment_s) + 1e-9).astype(int)
    return np.unique(raw, return_inverse=True)[1].reshape(-1).astype(int)


def sample_turn(session, names, setups: dict) -> np.ndarray:
    """(N,) max over sensors of |ω_i − b̂| dt_i (b̂ the N-pose gyro bias): rotation per sample interval, rad."""
    out = np.zeros(np.asarray(session.t).size)
    for name in names:
        s = session.sensors[name]
        out = np.maximum(out, np.linalg.norm(s.gyr - setups[name].gyro_bias0, axis=1) * s.dt)
    return out


def check_session(session) -> None:
    """Common time base and sample counts (SessionError otherwise)."""
    t = np.asarray(session.t, float)
    if t.ndim != 1 or t.size < 3 or np.any(np.diff(t) <= 0):
        raise SessionError(session.source, "t", f"shape {t.shape}", "(N,) strictly increasing times, N ≥ 3")
    for name, s in session.sensors.items():
        if s.t.shape != t.shape or np.max(np.abs(s.t - t)) > 1e-6:
            raise SessionError(session.source, f"sensors[{name}].t", f"{s.t.shape[0]} samples",
                               f"the session's {t.size} common sample times")
        for ch in ("gyr", "acc"):
            x = getattr(s, ch)
            if x.shape != (t.size, 3) or not np.all(np.isfinite(x)):
                raise SessionError(session.source, f"sensors[{name}].{ch}", f"shape {x.shape} or non-finite",
                                   f"({t.size}, 3) finite values")
