"""Maximum-likelihood magnetometer calibration in combination with inertial sensors, as a factor graph
(Kok, Hol, Schön, Gustafsson, Luinge, FUSION 2012; Kok & Schön, IEEE Sensors J. 2016, Algorithm 1).

    1. initial estimate: rest detection and noise from rest, ellipsoid fit, axis alignment and dip
       (imugraph.calibration.initial);
    2. repeat: preintegrate the gyro at the current bias; solve the MAP problem over keyframe
       orientations, gyro bias and θ = (D, o, δ) jointly (Python-driven LM); re-estimate Σω, Σa, Σm from
       the residuals (imugraph.calibration.noise) — until the noise levels and bias settle;
    3. marginal covariance of θ and the bias from the final linearisation.
"""

from __future__ import annotations

import sys
from copy import deepcopy
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from imugraph import keys
from imugraph.calibration.noise import field_dof, reestimate
from imugraph.calibration.rounds import fit_windows, solved_samples_block, thinned as _thinned
from imugraph.calibration.options import Options  # noqa: F401  (public here: ml.Options)
from imugraph.calibration.acc_timing import session_lead, with_lead
from imugraph.calibration.gyro_rate import update_rate_error
from imugraph.calibration.gyro_map_select import calibrate_chosen
from imugraph.calibration.result import Calibration, n_mag_from_dip
from imugraph.calibration.dip_fold import folded_dip, turn_quat, turn_vectors
from imugraph.factors.gaps import GAP_RATE_WALK, bias_segments
from imugraph.factors.gyro import keyframe_layout, preintegrate
from imugraph.calibration.disturbance import apply_windows, detect_windows
from imugraph.calibration.acc_rate import update_acc_rate_error
from imugraph.calibration.solution import marginal_covariances, per_sample_residuals  # noqa: F401 (public here)
from imugraph.factors.velocity import gravity_from_velocity
from imugraph.calibration.velocity_process import update_velocity_process
from imugraph.factors.theta import THETA_DIM, pack_theta, unpack_theta
from imugraph.graphs.orientation_init import complementary_keyframes, sample_orientations, window_orientations
from imugraph.calibration.gyro_map import GyroMapState, coverage_gate
from imugraph.calibration.initial import weak_initial  # noqa: F401  (re-exported: diagnose.fit uses it)
from imugraph.factors.field import field_key
from imugraph.graphs.single_imu import FieldModel, Noise, VelocityModel, build_problem, keyframe_rotations
from imugraph.graphs.gyro_map_block import without_map_keys
from imugraph.graphs.solver import keyframe_vectors, optimize
from imugraph.io.session import Session


@dataclass
class Estimate:
    """Result of calibration or smoothing: the calibration, per-sample orientation and residuals."""

    calibration: Calibration
    t: np.ndarray
    quat: np.ndarray                     # (N, 4) nRb w,x,y,z
    residuals: dict                      # channel → (N, 3) whitened residuals, NaN where no sample
    info: dict


def stride_for(session: Session, keyframe_hz: float) -> int:
    return max(1, int(round(session.rate / keyframe_hz)))


def gravity_from(session: Session, rest: np.ndarray | None) -> float:
    norms = np.linalg.norm(session.acc, axis=1)
    if rest is not None and rest.sum() > 10:
        return float(np.median(norms[rest]))
    return float(np.median(norms))


def calibrate(session: Session, options: Options | None = None, initial=None,
              allow_weak: bool = False) -> Estimate:
    """Estimate D, o, dip, gyro bias, noise levels and the smoothed orientation of a session.

    Args:
        allow_weak: when the data do not identify D and o (too little rotation, or an ellipsoid fit
            broken by a disturbance), fall back to a regularised estimate around a sphere (D = s·I, o = 0,
            tight prior) instead of raising; `coverage["identifiable"]` is then False with the reason.

    Raises:
        CalibrationError: the data do not allow a calibration (named problem, e.g. too little rotation).
    """
    from imugraph.errors import CalibrationError

    opt = options or Options()
    if opt.field_select or opt.gyro_map_select:   # chosen per recording by held-out prediction (field_select.py,
        return calibrate_chosen(session, opt, initial, allow_weak)   # gyro_map_select.py)
    weak_reason = None
    if initial is None:
        from imugraph.calibration.initial import initial_calibration
        try:
            initial = initial_calibration(session)
        except CalibrationError as exc:
            if not allow_weak:
                raise
            weak_reason = str(exc)
            initial = weak_initial(session, weak_reason, opt.weak_mag_delay)
    init = initial
    delay = float(getattr(init, "mag_delay_s", 0.0)) if opt.compensate_mag_delay else 0.0
    if delay != 0.0:
        from imugraph.calibration.alignment import undelay_magnetometer
        session = session.with_mag(undelay_magnetometer(session.t, session.mag, delay))
    lead = session_lead(session) if opt.acc_lead_samples is None else float(opt.acc_lead_samples)
    session = with_lead(session, lead)       # accelerometer–gyro sample timing (calibration/acc_timing.py)
    g = gravity_from(session, getattr(init, "rest", None))
    noise = Noise(np.asarray(init.noise["gyr"], float), np.asarray(init.noise["acc"], float),
                  np.asarray(init.noise["mag"], float))
    theta0 = pack_theta(init.D, init.o, init.dip_rad)
    bias = np.asarray(init.gyro_bias, float)
    stride = stride_for(session, opt.keyframe_hz)
    kf, skf = keyframe_layout(session.n, stride, session.dt if opt.gap_model else None)
    m_cal0 = np.linalg.solve(init.D, (session.mag - init.o).T).T
    nRk = None
    theta = theta0
    seg = _bias_segments(session, kf, opt.bias_segment_s)
    n_seg = int(seg.max()) + 1 if len(seg) else 1
    bias = np.tile(bias, (n_seg, 1))
    history = []
    tau_fixed = None
    converged = False
    theta_sigma = _theta_prior_sigma(theta0, weak_reason is not None, opt.weak_theta_fraction)

    rest_mask = getattr(init, "rest", None) if opt.zero_velocity_at_rest else None

    vel_state = {"v": None, "s": None, "sigma": opt.velocity_sigma, "tau": opt.velocity_tau, "g": None,
                 "rest": rest_mask, "ar2": None, "kappa_a": opt.acc_rate_error,
                 "pos_sigma": (opt.position_sigma or 1.0) if opt.estimate_position_sigma else opt.position_sigma}
    if opt.estimate_velocity_process == "hetero_ar2":   # motion intensity per interval (velocity_hetero.py)
        from imugraph.calibration.velocity_hetero import calibration_intensity
        vel_state["intensity"] = calibration_intensity(session.acc, g, skf, len(kf))
    windows = detect_windows(session.t, m_cal0) if opt.disturbance_windows else []
    mag_state = {"y": session.mag, "w": apply_windows(windows, session.mag)[1] if windows else None}

    round_solver = opt.solver if opt.round_relative_tol is None else replace(
        opt.solver, relative_tol=opt.round_relative_tol)
    round_every = max(1, stride // opt.round_min_samples)   # the rounds' magnetometer thinning

    if opt.gyro_map_fallback not in ("warm", "restart"):
        raise ValueError(f"Options.gyro_map_fallback: found {opt.gyro_map_fallback!r}, expected 'warm' or 'restart'")
    gate, clean = coverage_gate(session, g, skf, len(kf) - 1, opt) if opt.gyro_map else ({"estimated": False}, None)
    gyro = GyroMapState(opt.gyro_map_sigma, clean if gate["estimated"] else None, session.meta.get("gyro_map_exclude"))
    rate = {"kappa": opt.gyro_rate_error}      # κ, re-estimated with estimate_gyro_rate_error
    field_state = {"sigma": opt.field_sigma}   # σ_d of the final solve (Options.position_select_field may change it)

    pre_memo = {}                              # the last preintegration without the gyro map (J2 CPU options)
    def solve_round(bias, noise, nRk, theta, every=1, final=False, values0=None, solver=None):
        """Preintegrate at the current bias, build the graph, solve it (one round of the ML loop);
        values0: the previous round's solution, which holds exactly nRk, bias, θ and the velocities."""
        with_map = phase["map"] and (opt.gyro_map_final or not final)
        # (J2) candidates share bias, noise, κ and Ê: their preintegration is the same (read-only), reused
        memo = (np.asarray(bias).tobytes(), np.asarray(noise.gyr).tobytes(), rate["kappa"], gyro.E.tobytes())
        if not with_map and pre_memo.get("key") == memo:
            pre = pre_memo["pre"]
        else:
            g_c, b_rows = gyro.corrected(session.gyr), _per_sample_bias(bias, seg, skf)
            pre = preintegrate(g_c, session.dt, kf, skf, b_rows, noise.gyr, rate["kappa"], keep_steps=with_map,
                               gap_walk=GAP_RATE_WALK if opt.gap_model else None)
            pre_memo.update(key=None if with_map else memo, pre=pre)
        gmap = gyro.model(g_c, session.dt, pre, b_rows) if with_map else None
        if gmap is None and values0 is not None:       # the rounds' β_k and e are not in this graph
            values0 = without_map_keys(values0)
        start = complementary_keyframes(pre, session.acc, m_cal0) if nRk is None else nRk
        velocity = _velocity_model(opt, vel_state)
        g_round = vel_state["g"] or g
        prob = build_problem(pre, session.acc, _thinned(mag_state["y"], every), noise, g_round, start,
                             bias, theta,
                             theta_prior_sigma=theta_sigma, bias_prior_sigma=opt.bias_prior_sigma,
                             acc_kernel=opt.acc_kernel, mag_kernel=opt.mag_kernel,
                             bias_segment=seg, bias_rw_sigma=opt.bias_rw, velocity=velocity, dt=session.dt,
                             mag_weights=mag_state["w"], values0=values0,
                             field=None if field_state["sigma"] is None else FieldModel(field_state["sigma"],
                                                                                        opt.field_tau),
                             gyro_map=gmap)
        values, info = optimize(prob.graph, prob.blocks, prob.values, prob.ordering,
                                solver or (opt.solver if final else round_solver))   # solver: (J2) candidates
        if gmap is not None:
            gyro.fold(values)
        if prob.block.with_field:      # residuals, noise levels and windows at the solution's field perturbation
            prob.block.field_offsets = keyframe_vectors(values, field_key, len(kf))
        if velocity is not None:
            vel_state["s"] = keyframe_vectors(values, keys.vel, len(kf))
            vel_state["v"] = vel_state["s"][:, :3]
            vb = prob.velocity
            dv = vb.dv if vb.B is None else vb.dv - np.einsum("kij,kj->ki", vb.B, vel_state["s"][:-1, 3:])
            vel_state["g"] = gravity_from_velocity(keyframe_rotations(values, len(kf)), dv, pre.dt)
        return pre, prob, values, info

    phase = {"map": False}      # True while Ê is estimated (the rounds' graphs get the gyro-map block)

    def ml_rounds(bias, noise, nRk, theta, values):
        """Step 2 until the noise levels and bias (and Ê, in the gyro-map phase) settle, from a state
        (values None: no previous solution). Returns bias, noise, nRk, θ, values, converged."""
        nonlocal tau_fixed, opt
        if values is None and opt.estimate_bias_rw:     # fresh rounds start from the configured q
            opt = replace(opt, bias_rw=(options or Options()).bias_rw)
        converged = False
        for outer in range(1, opt.max_outer + 1):
            pre, prob, values, info = solve_round(bias, noise, nRk, theta, round_every,
                                                  values0=values)
            nRk = keyframe_rotations(values, len(kf))
            theta = values.atVector(keys.CALIB)
            bias_new = _bias_values(values, n_seg)
            history.append({"outer": len(history) + 1, "lm_iterations": info.iterations, "cost": info.cost_final,
                            "noise": {k: np.asarray(v).tolist() for k, v in noise.as_dict().items()}})
            if not opt.reestimate_noise:
                bias = bias_new
                converged = info.converged
                break
            extra = None
            if prob.block.with_field and prob.block.mag is not None:   # d_k absorbs part of the field residuals
                sig_d = field_state["sigma"] if opt.position_select_field_rounds else opt.field_sigma   # (J2)
                extra = {"mag": field_dof(prob.block.field_information(nRk, theta), pre.dt, sig_d,
                                          opt.field_tau)}
            block = solved_samples_block(prob.block) if opt.noise_skip_excluded else prob.block
            new = reestimate(block, nRk, theta, pre.cov, values, noise.gyr, extra)   # cov: AHRS factors' Σ
            taus = {c: new.pop(c + "_tau") for c in ("acc", "mag") if c + "_tau" in new}
            if opt.correlated_noise:
                # τ from the first (white-noise) solution only: later solutions lean on the gyro and their
                # residuals inherit its drift, which would feed back into τ. Capped at max_corr_s.
                if tau_fixed is None:
                    cap = max(1.0, opt.max_corr_s * session.rate)
                    tau_fixed = {c: min(t, cap) for c, t in taus.items()}
                for c, tau in tau_fixed.items():
                    new[c] = new[c] * np.sqrt(tau)
            history[-1]["tau"] = taus
            change = max(float(np.max(np.abs(np.log(new[c] / getattr(noise, c))))) for c in new)
            if opt.estimate_gyro_rate_error:  # κ by an ML step (calibration/gyro_rate.py)
                change = max(change, update_rate_error(rate, prob, values, pre, history[-1]))
            change = max(change, update_acc_rate_error(opt, vel_state, prob.velocity, nRk, pre, session, history[-1]))
            if vel_state["v"] is not None and opt.estimate_velocity_process != "off":   # EM step of σ_v, τ_v
                change = max(change, update_velocity_process(vel_state, prob.velocity, nRk, history[-1],
                                                             opt.estimate_velocity_process, opt.velocity_sigma,
                                                             opt.velocity_tau, opt.velocity_prior_strength,
                                                             opt.velocity_em_inner))
            if opt.estimate_position_sigma and prob.velocity is not None and prob.velocity.position is not None:
                from imugraph.calibration.position_process import update_position_sigma   # EM step of σ_p (J1)
                from imugraph.graphs.velocity_block import pos_key
                change = max(change, update_position_sigma(
                    vel_state, prob.velocity, nRk, keyframe_vectors(values, pos_key, len(kf)), opt.position_tau,
                    opt.position_em_inner, history[-1]))
            if opt.estimate_bias_rw:    # EM step of the gyro-bias random-walk density (calibration/bias_process.py)
                from imugraph.calibration.bias_process import em_bias_rw
                opt, change = em_bias_rw(opt, prob, values, pre, n_seg, history[-1], change)
            if windows:
                # windowed hard iron at the current orientations (linear given them), Kok's o + Δo_w
                D_, o_, dip_ = unpack_theta(theta)
                nRb = window_orientations(windows, nRk, pre)
                n_nav = n_mag_from_dip(dip_)
                if prob.block.field_offsets is not None:          # n + d_k of each sample's keyframe
                    n_nav = n_nav + prob.block.field_offsets[pre.sample_kf]
                change = max(change, fit_windows(windows, opt, session, nRk, pre, D_, o_, n_nav, nRb,
                                                 float(np.sqrt(np.mean(noise.mag ** 2)))))    # rounds.py
                mag_state["y"], mag_state["w"] = apply_windows(windows, session.mag)
                history[-1]["windows"] = [w.as_dict(session.t) for w in windows]
            if phase["map"]:
                history[-1]["gyro_map"] = gyro.E.tolist()
                change = max(change, gyro.step / opt.gyro_map_tol * opt.noise_tol)     # E settled
                steps = gate.setdefault("steps", [])
                steps.append(gyro.step)
                if len(steps) > 1 and steps[-1] > opt.gyro_map_max_contraction * steps[-2]:
                    break                  # creeping: the settling gate fails whatever follows (BROAD 24)
            bias_change = float(np.max(np.linalg.norm(bias_new - bias, axis=1)))
            noise = Noise(new.get("gyr", noise.gyr), new.get("acc", noise.acc), new.get("mag", noise.mag))
            bias = bias_new
            if opt.progress:
                print(f"  ML round {len(history)}: LM {info.iterations} it, noise change {change:.3f}, "
                      f"bias change {np.rad2deg(bias_change):.4f} °/s", file=sys.stderr)
            if change < opt.noise_tol and bias_change < 1e-4:
                converged = True
                break
        return bias, noise, nRk, theta, values, converged

    if gate["estimated"]:
        # E from the first round; the plain model's starting state is kept so that, if Ê does not settle,
        # the plain rounds run from it (the result is exactly the plain model's, without redoing step 1)
        start = (bias, noise, dict(vel_state), dict(mag_state), deepcopy(windows))
        phase["map"] = True
        bias, noise, nRk, theta, values, converged = ml_rounds(bias, noise, nRk, theta, None)
        steps = gate.get("steps", [])
        gate["contraction"] = steps[-1] / steps[-2] if len(steps) > 1 and steps[-2] > 0 else None
        if not converged or gate["contraction"] is None or gate["contraction"] > opt.gyro_map_max_contraction:
            # Ê still moving after max_outer rounds, or creeping (a round's step > half the previous): E
            # is set by what a round freezes (intra-interval rotations, velocity increments, windows), not
            # determined by the joint solve (BROAD 24, tapping: an off-diagonal crept to −0.8 %, 0.51 → 0.73°;
            # zeroing Ê for the final solve alone still gave 0.72°): the plain model's result instead
            gate.update(estimated=False, reason=f"E did not settle in the ML rounds (contraction "
                        f"{gate['contraction']})", E_unsettled=gyro.E.copy(), rounds=list(history),
                        fallback=opt.gyro_map_fallback)
            if opt.gyro_map_fallback == "restart":     # the plain rounds from step 1's state: bit-identical
                bias, noise, nRk, theta, tau_fixed, values = start[0], start[1], None, theta0, None, None
                vel_state.update(start[2]); mag_state.update(start[3]); windows[:] = start[4]
            # "warm": the plain rounds continue from the E rounds' state (rotations, bias, θ, noise, τ,
            # velocities, windows) with Ê = 0 — the plain model's ML fixed point from a nearer start
            del history[:]
            if opt.progress:       # the rounds are numbered from 1 again: say why (U22 #15, "ML round 1" twice)
                print("  gyro scale/misalignment E did not settle: ML rounds again without it", file=sys.stderr)
            gyro.E, phase["map"], rate["kappa"] = np.zeros((3, 3)), False, opt.gyro_rate_error
            bias, noise, nRk, theta, values, converged = ml_rounds(bias, noise, nRk, theta, values)
    else:
        bias, noise, nRk, theta, values, converged = ml_rounds(bias, noise, nRk, theta, None)
    gate.setdefault("contraction", None)

    # final solve at the converged noise levels and bias, then marginals
    if opt.position_select:      # σ_p by the Laplace marginal likelihood, "off" among the candidates (J2)
        from imugraph.calibration.position_select import final_with_selection
        (pre, prob, values, info), (bias, noise, nRk, theta, converged) = final_with_selection(
            solve_round, ml_rounds, vel_state, opt, (bias, noise, nRk, theta, values, converged), len(kf), round_every,
            history, field_state, gyro, round_solver)
    else:
        pre, prob, values, info = solve_round(bias, noise, nRk, theta, final=True, values0=values)
    nRk = keyframe_rotations(values, len(kf))
    theta = values.atVector(keys.CALIB)
    bias_segments = _bias_values(values, n_seg)
    bias = bias_segments.mean(axis=0)
    try:
        cov_theta, cov_bias = marginal_covariances(prob, values)
    except RuntimeError:     # indeterminate: some direction of θ is not observable (reported as NaN)
        cov_theta, cov_bias = np.full((THETA_DIM, THETA_DIM), np.nan), np.full((3, 3), np.nan)
    D, o, dip = unpack_theta(theta)
    dip, folded = folded_dip(dip)     # δ → π − δ past 90°, nav frame turned by Rz(π) below (dip_fold.py, U22 #1)
    std_theta = np.sqrt(np.maximum(np.diag(cov_theta), 0.0))
    cal = Calibration(
        D=D, o=o, dip_deg=float(np.rad2deg(dip)), gyro_bias=bias,
        noise=noise.as_dict(),
        std={"D": std_theta[:9].reshape(3, 3), "o": std_theta[9:12], "dip_deg": float(np.rad2deg(std_theta[12])),
             "gyro_bias": np.sqrt(np.maximum(np.diag(cov_bias), 0.0))},
        coverage=getattr(init, "coverage", {}) or {}, converged=bool(converged and info.converged),
        iterations=len(history), mag_delay_s=delay, disturbances=[w.as_dict(session.t) for w in windows],
        gyro_map=gyro.E.copy(), acc_lead_samples=lead,
        **_velocity_process(opt, vel_state))
    residuals = per_sample_residuals(prob, nRk, theta, session)
    if opt.heading_only_orientation and prob.block.mag is not None:
        from imugraph.graphs.heading_block import heading_only_rotations
        nRk = heading_only_rotations(session, opt, pre, values, noise, g_used=vel_state["g"] or g, theta=theta,
                                     bias=bias_segments, seg=seg, mag_state=mag_state,
                                     velocity=_velocity_model(opt, vel_state))
    quat = sample_orientations(nRk, pre)
    field_offsets, velocity = prob.block.field_offsets, vel_state["v"]
    if folded:                        # the same optimum in DESIGN's convention: nRb, v_k, d_k turned by Rz(π)
        quat, field_offsets, velocity = turn_quat(quat), turn_vectors(field_offsets), turn_vectors(velocity)
    return Estimate(cal, session.t, quat, residuals,
                    {"history": history, "keyframes": len(kf), "stride": stride, "g": vel_state["g"] or g,
                     "gyro_bias_segments": bias_segments, "noise_correlation": tau_fixed or {},
                     "lm_iterations_final": info.iterations, "final_cost": (info.cost_initial, info.cost_final),
                     "velocity": velocity, "dip_folded": folded,
                     "acc_bias": (None if vel_state["s"] is None or vel_state["s"].shape[1] < 6
                                  else vel_state["s"][:, 3:].mean(axis=0)),
                     "velocity_sigma": vel_state["sigma"], "velocity_tau": vel_state["tau"],
                     "position_sigma": vel_state.get("pos_sigma"), "final_field_sigma": field_state["sigma"],
                     "disturbance_windows": [w.as_dict(session.t) for w in windows], "keyframe_samples": kf,
                     "field_offsets": field_offsets, "gyro_map": gyro.E,
                     "gyro_map_gate": gate, "gyro_rate_error": rate["kappa"]})


def _velocity_process(opt: Options, vel: dict) -> dict:
    """σ_v, τ_v for the Calibration when the ML loop estimated them as scalars (else {}: not recorded); with the
    AR(2) process, its first-order equivalent (√γ₀, τ from ρ₁: velocity_ar2), as smooth_fixed and the stream take."""
    if opt.estimate_velocity_process == "off" or np.ndim(vel["sigma"]) or np.ndim(vel["tau"]):
        return {}
    return {"velocity_sigma": float(vel["sigma"]), "velocity_tau": float(vel["tau"])}


def _velocity_model(opt: Options, vel: dict) -> VelocityModel | None:
    """The velocity chain's settings for the next solve (None: linear acceleration treated as noise)."""
    if opt.linear_acceleration != "velocity":
        return None
    return VelocityModel(vel["sigma"], vel["tau"], vel.get("kappa_a", opt.acc_rate_error), opt.acc_kernel, vel["s"],
                         opt.acc_bias, rest=vel["rest"], ar2=vel.get("ar2"),
                         position=None if vel.get("pos_sigma") is None else (vel["pos_sigma"], opt.position_tau))


def _bias_segments(session: Session, kf: np.ndarray, segment_s: float) -> np.ndarray:
    """Bias segment index (K−1,) of each keyframe interval."""
    return bias_segments(session.t[kf[:-1]] - session.t[0], segment_s)


def _per_sample_bias(bias: np.ndarray, seg: np.ndarray, skf: np.ndarray) -> np.ndarray:
    """(N, 3) bias of each sample from the (S, 3) segment biases."""
    if len(seg) == 0:
        return np.broadcast_to(bias[0], (len(skf), 3)).copy()
    return bias[seg[np.minimum(skf, len(seg) - 1)]]


def _bias_values(values: gtsam.Values, n_seg: int) -> np.ndarray:
    return np.stack([values.atVector(keys.bias(i)) for i in range(n_seg)])


def _theta_prior_sigma(theta0: np.ndarray, tight: bool = False, fraction: float = 0.05) -> np.ndarray:
    """Prior on θ: weak (D entries ± its scale, o ± 2 field norms, dip ± 90°), or tight around a sphere
    (D ± `fraction` of the scale, o ± twice that; Options.weak_theta_fraction) when the data do not identify D, o."""
    D0, _, _ = unpack_theta(theta0)
    s = float(np.cbrt(abs(np.linalg.det(D0)))) or 1.0
    f = max(float(fraction), 1e-6) if tight else 1.0
    return np.concatenate([np.full(9, f * s), np.full(3, 2.0 * f * s), [np.pi / 2]])
