"""Sensor headings on their segments from the motion itself (BodyOptions.init = "motion", `mocap --init motion`).

Why: the body estimator starts every sensor at the heading its NOMINAL placement implies (imugraph.body.placement,
Xsens-style sites). A real suit strapped on another way (qmt's full-body example: the upper-back sensor on the
back, 180° from the nominal sternum site; legs and arms 20–290° off) starts LM so far from the minimum that it
stops at its iteration limit with knees through ±180° (docs/results_issue4.md, session 22, helper Q). Here each
sensor's turn about the vertical at the N-pose is found from the joint accelerations instead (IMU samples only).

Assumes: an N-pose (npose_samples) in which the tilt of every sensor is its accelerometer's; a segment tree whose
joints are (approximately) ball joints seen by both sensors' accelerations; at least a few seconds of motion with
angular accelerations after the N-pose (`window_s`); no magnetometer is used. What it does not fix: the sensors'
positions on the segments (b_pos stays nominal) and the tilt (the N-pose's gravity fixes it, as in body_init).

With the N-pose tilt and the gyro integrated from it (body_init.initial_orientations, nominal headings), each
joint (topological order, the root's heading kept) gets the heading turn δ of its child sensor that best explains
one joint centre seen from both sides (the joint-acceleration constraint of Seel, Schauer & Raisch 2012, with the
levers fitted, not assumed):

    n_a_s = nRs f_s − g ẑ,   K_s = nRs ([ω̇_s×] + [ω_s×]²)                                          (H1)
    n_a_P + K_P l_P = Rz(δ) (n_a_C + K_C l_C)      (l_P, l_C least squares for each δ)              (H2)
    δ_C = argmin_δ RMS residual of (H2) over `window_s` after the N-pose (grid `step_deg`)        (H3)
    ψ: (O1) of body_output.npose_heading on the N-pose joint centres chained from the root with the
       fitted levers,  J = p_P + nRs_P l_P,  p_C = J − nRs_C l_C                                     (H4)

Placement: bRs = Rz(ψ)ᵀ Rz(δ_C) nRs(N-pose) (the segments world-aligned at the N-pose, facing ψ), b_pos nominal.
Without (H4) every lever prior would turn with the root sensor's unknown heading.

BodyOptions.init "auto" uses these placements only for the sensors more than init_motion_switch_deg (45°) from their
nominal one (`with_motion_placements`): measured (docs/results_issue4.md, session 22 helper Q22b), "motion" for every
sensor costs the short CMU simulations up to 0.6° (batch) while "auto" leaves them unchanged and still fixes qmt's file.
"""

from __future__ import annotations

import numpy as np

from imugraph.geometry import skew as _skew


def _joint_fit(aP: np.ndarray, KP: np.ndarray, aC: np.ndarray, KC: np.ndarray, d_deg: float) -> tuple:
    """(δ deg, RMS m/s², [l_P, l_C]) of (H2) with the child turned by δ: levers by linear least squares."""
    from imugraph.graphs.body_init import rz

    Rd = rz(np.radians(d_deg))
    A = np.concatenate([KP, -(Rd @ KC)], axis=2).reshape(-1, 6)              # K_P l_P − Rz(δ) K_C l_C = …   (H2)
    b = (aC @ Rd.T - aP).reshape(-1)                                          # … = Rz(δ) n_a_C − n_a_P
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    return float(d_deg) % 360.0, float(np.sqrt(np.mean((A @ sol - b) ** 2))), sol


def motion_placements(session, opts, npose_idx: np.ndarray | None = None, window_s: float = 30.0,
                      step_deg: float = 5.0) -> tuple[dict, dict]:
    """({segment: (bRs, b_pos)} for BodyOptions.placements, info) from (H1)–(H4) (module docstring).

    session: a BodySession with a skeleton; opts: BodyOptions (npose, g, and any placements already given: those
    fix the tilt start of their sensors); npose_idx: the N-pose samples (None: body_model.npose_samples).
    info: {child: {"delta_deg", "rms_m_s2", "levers"}, "_psi_deg": ψ}; ({}, {"skipped": why}) when the session
    has no joints or no sample after the N-pose."""
    from imugraph.graphs.body_init import initial_orientations, rz
    from imugraph.graphs.body_model import body_joints, npose_samples, sensor_setup

    skel = session.skeleton
    names = sorted(skel.sensed, key=skel.index)
    joints = body_joints(skel)
    if npose_idx is None:
        npose_idx, _ = npose_samples(session, opts)
    n_samples, rate = session.t.size, 1.0 / float(np.median(np.diff(session.t)))     # any session with t (BodySession or not)
    w = slice(int(npose_idx[-1]) + 1, min(n_samples - 1, int(npose_idx[-1]) + 1 + int(window_s * rate)))
    if not joints or w.stop - w.start < 3:
        return {}, {"skipped": "no joints" if not joints else "no motion after the N-pose"}
    setups = sensor_setup(session, skel, opts, npose_idx)
    R = initial_orientations(session, names, setups, npose_idx, 0.0, False, stop=w.stop)     # only [:w.stop] is used
    acc_n, K = {}, {}
    for n in names:
        s = session.sensors[n]
        om = s.gyr - setups[n].gyro_bias0
        dom = np.gradient(om, s.t, axis=0)
        acc_n[n] = np.einsum("nij,nj->ni", R[n][w], s.acc[w]) - np.array([0.0, 0.0, opts.g])          # (H1)
        K[n] = R[n][w] @ (_skew(dom[w]) + _skew(om[w]) @ _skew(om[w]))
    turn, info = {names[0]: 0.0}, {}
    for jt in joints:
        P, C = jt.parent, jt.child
        RzP = rz(np.radians(turn[P]))
        aP, KP = acc_n[P] @ RzP.T, RzP @ K[P]
        best = min((_joint_fit(aP, KP, acc_n[C], K[C], d) for d in np.arange(0.0, 360.0, step_deg)),
                   key=lambda r: r[1])
        turn[C] = best[0]                                                                                  # (H3)
        info[C] = {"delta_deg": best[0], "rms_m_s2": best[1], "levers": best[2]}
    R0 = {n: rz(np.radians(turn[n])) @ R[n][int(npose_idx[0])] for n in names}
    pos, J, c = {names[0]: np.zeros(3)}, [], []
    neutral = skel.neutral_positions()
    for jt in joints:                                                                                      # (H4)
        l_P, l_C = info[jt.child]["levers"][:3], info[jt.child]["levers"][3:]
        J.append(pos[jt.parent] + R0[jt.parent] @ l_P)
        pos[jt.child] = J[-1] - R0[jt.child] @ l_C
        c.append(neutral[skel.index(jt.child)])
    u, d = (np.array(c) - np.mean(c, axis=0))[:, :2], (np.array(J) - np.mean(J, axis=0))[:, :2]
    psi = float(np.arctan2(np.sum(u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0]), np.sum(u * d)))                 # (O1)
    place = {n: (rz(psi).T @ R0[n], setups[n].b_pos_nom) for n in names}
    for v in info.values():
        v["levers"] = np.round(v["levers"], 4).tolist()
    info["_psi_deg"] = float(np.degrees(psi))
    return place, info


def with_motion_placements(session, opts, npose_idx: np.ndarray) -> tuple[object, dict | None]:
    """(opts, info) for BodyOptions.init:
        "nominal"  (opts, None): unchanged;
        "motion"   opts.placements from `motion_placements` for every sensed segment not already given there;
        "auto"     the same, but only for the sensors whose motion placement is more than
                   opts.init_motion_switch_deg from their nominal one (angle of bRs_nomᵀ bRs_motion): a sensor
                   strapped on far from the nominal site; the others keep the nominal start (on the 4a
                   simulations, placements ≤ 30° off, no sensor switches: the nominal start's results exactly).
    Placements given in opts.placements always win. info: motion_placements' info (+ "_switched" for "auto")."""
    from dataclasses import replace

    from imugraph.geometry import logmap
    from imugraph.graphs.body_model import default_placement

    init = getattr(opts, "init", "nominal")
    if init not in ("nominal", "motion", "auto"):
        raise ValueError(f"BodyOptions.init {init!r}: expected 'nominal', 'motion' or 'auto'")
    if init == "nominal":
        return opts, None
    place, info = motion_placements(session, opts, npose_idx, window_s=opts.init_motion_window_s)
    if init == "auto":
        far = {n: float(np.degrees(np.linalg.norm(logmap(default_placement(session.skeleton, n)[0].T @ p[0]))))
               for n, p in place.items()}
        place = {n: p for n, p in place.items() if far[n] > opts.init_motion_switch_deg}
        info["_switched"] = {n: round(far[n], 1) for n in place}
    return replace(opts, placements={**place, **opts.placements}), info
