"""σ_p of the bounded position chosen per recording by the Laplace marginal likelihood, "off" included (task J).

Why not EM (calibration/position_process.py, (J1)): its covariances hold the orientations, and the bound is
satisfied by bending the tilt — a travelling sensor's positions then shrink to the prior, and EM follows them
down (benchmarks/j2_travel.py: a simulated 200 m walk, σ̂_p → 0.5 m, +0.6°). Whether the data prefer a bound is
a question for the WHOLE posterior: a bound that forces the tilt off the gyro's and the magnetometer's evidence
costs fit, one that only removes a phantom velocity costs almost none and is rewarded by the smaller posterior
volume (Occam factor). With everything else at the ML loop's converged noise levels, each candidate σ is one
joint solve and

    ln Z(σ) = −C_σ(x̂_σ) − ½ ln det H_σ + ½ ln det Λ_σ  + const                                             (J2)

C_σ: the graph's total cost at its minimiser (½ Σ r², all factors incl. the velocity and position priors);
H_σ: its Gauss–Newton Hessian there (GTSAM elimination: ln det H = 2 Σ ln |R_ii|); Λ_σ: the precision of the
PRIOR of the velocity/position states alone (velocity process, kinematic rows (P1), position prior; the same
(v, p) chain as (J1) without the accelerometer rows), whose ½ ln det is the normaliser of that prior — the
positions are integrals of the velocities, so the product of the velocity process and (P1) is normalised anew for
every σ. Terms that do not depend on σ (measurement normalisers, 2π's) cancel. "Off" is the candidate
σ → ∞ limit: the plain solve without a position state, scored with its velocity-process prior alone (the
position's rows cancel between H_σ and Λ_σ). Every candidate's cost is evaluated with the robust kernels as ρ.
Pick argmax; candidates within EVIDENCE_MARGIN nats of it go to the looser bound (the defaults win ties).

Flow (`final_with_selection`, Options.position_select): after the ML rounds converged without a position state,
every candidate is solved from the same state; with Options.position_select_rounds the candidates are solved as a
round is (thinned magnetometer: cheaper) and a chosen bound runs the ML rounds again under it before the final
solve (on BROAD 02 the bound then also reaches the noise levels and bias: 0.436° → 0.404°); "off" gives exactly
the defaults' final solve (tests/test_position_select.py). Options.position_select_field adds candidates for the
field perturbation's cross-field σ (scored with that prior's normaliser, `field_half_logdet`): measured, mixed
(docs/results_issue2.md session 17). Task J2: Options.position_select_field_rounds scores σ_d,y instead after the
bound's ML rounds (`field_after_rounds`: at their noise levels, then the rounds again at a chosen σ_d,y, whose dof
charge the Σm re-estimate uses) — on BROAD the evidence keeps σ_y = 0.003 on 10 of the 12 bounded trials by 4–38
nats; Options.position_select_max_iter=1 (one LM step per candidate from the converged state) keeps every choice
and cuts ≈ 0.2–0.4 s CPU; position_select_stop (stop when ln Z drops) changes BROAD 01's choice: ln Z(σ_p) is not
unimodal there (session 17, helper J2).
"""

from __future__ import annotations

import copy
from dataclasses import replace

import gtsam
import numpy as np
from scipy.linalg import cholesky_banded

from imugraph.calibration.position_process import vp_bands
from imugraph.calibration.velocity_process import chain_bands
from imugraph.graphs.solver import total_cost

OFF_SIGMA = 1.0e4          # m: the "off" candidate
EVIDENCE_MARGIN = 3.0      # nats: a candidate replaces the looser one (or the configured field) only with ln B ≥ 3,
#                            "strong" evidence on Kass & Raftery's (1995) scale (2 ln B > 6); a simulated walk
#                            (benchmarks/j2_travel.py seed 2) scores σ_p = 3 m 0.3 nats above "off"


def posterior_half_logdet(prob, values) -> float:
    """½ ln det of the Gauss–Newton Hessian of the whole problem at `values` (Σ ln |R_ii| of its elimination)."""
    gfg = prob.graph.linearize(values)
    for b in prob.blocks:
        gfg.push_back(b.linearize(values))
    return float(gfg.eliminateSequential(prob.ordering).logDeterminant())


def prior_half_logdet(block, nRk: np.ndarray, s: np.ndarray, sigma_p: float | None, tau_p: float) -> float:
    """½ ln det Λ_σ of (J2): the (v, p) chain's prior precision (no accelerometer rows), three equal axes;
    sigma_p None: the velocity chain's alone (no position state: the σ → ∞ limit of (J2))."""
    b = copy.copy(block)
    b.fixed_weights = np.zeros(block.n_keyframes - 1)          # a = w/σ² = 0: the increments left out
    ab = chain_bands(b, nRk, s)[:, :, 0] if sigma_p is None else vp_bands(b, nRk, s, sigma_p, tau_p)
    c = cholesky_banded(ab, lower=True)
    return 3.0 * float(np.sum(np.log(c[0])))


def robust_cost(prob, values) -> float:
    """The problem's total cost with the velocity block's robust kernel evaluated as ρ (not the per-solve held
    weights' quadratic), so that every candidate, with or without a position state, is scored alike."""
    vb = prob.velocity
    held = None if vb is None else vb.fixed_weights
    if vb is not None:
        vb.fixed_weights = None
    try:
        return total_cost(prob.graph, prob.blocks, values)
    finally:
        if vb is not None:
            vb.fixed_weights = held


def log_evidence(prob, values, sigma_p: float | None, tau_p: float, nRk: np.ndarray, s: np.ndarray) -> dict:
    """(J2) of one candidate's solve: prob (its VelocityBlock `prob.velocity` carrying the position, or none:
    sigma_p None) and the solution `values`. Returns the parts and the sum."""
    cost = robust_cost(prob, values)
    half_post = posterior_half_logdet(prob, values)
    half_prior = prior_half_logdet(prob.velocity, nRk, s, sigma_p, tau_p)
    return {"sigma_p": OFF_SIGMA if sigma_p is None else float(sigma_p), "cost": float(cost),
            "half_logdet_post": half_post, "half_logdet_prior": half_prior,
            "log_z": float(-cost - half_post + half_prior)}


def choose(scores: list[dict], margin: float = 0.0) -> dict:
    """The candidate of largest ln Z; within `margin` nats of it, the loosest (largest σ_p) wins."""
    best = max(s["log_z"] for s in scores)
    ok = [s for s in scores if s["log_z"] >= best - margin]
    return max(ok, key=lambda s: s["sigma_p"])


def field_half_logdet(dt_k: np.ndarray, sigma_d, tau_d: float) -> float:
    """½ ln det of the field perturbation's prior precision (factors/field.py: stationary Gauss–Markov per nav axis,
    d_0 ~ N(0, σ_a²), steps φ_k, σ_a² (1 − φ_k²)): −Σ_a [K ln σ_a + ½ Σ_k ln(1 − φ_k²)]."""
    from imugraph.factors.field import field_sigmas
    phi = np.exp(-np.asarray(dt_k, float) / max(float(tau_d), 1e-9))
    K = len(dt_k) + 1
    sig = field_sigmas(sigma_d)
    return float(-np.sum(K * np.log(sig) + 0.5 * np.sum(np.log(np.maximum(1.0 - phi**2, 1e-300)))))


def _snapshot(vel_state: dict, gyro):
    """A function restoring vel_state and the GyroMapState's (Ê, step) to what they are now (candidates' start)."""
    saved = dict(vel_state)
    g0 = (gyro.E.copy(), gyro.step)

    def restore():
        vel_state.clear(); vel_state.update(saved)
        gyro.E, gyro.step = g0[0].copy(), g0[1]
    return restore


def _score(prob, values, sigma_p, opt, K, field_sigma):
    from imugraph import keys
    from imugraph.graphs.solver import keyframe_rotations, keyframe_vectors

    sc = log_evidence(prob, values, sigma_p, opt.position_tau, keyframe_rotations(values, K),
                      keyframe_vectors(values, keys.vel, K))
    if field_sigma is not None:          # the field prior's normaliser: differs between σ_d candidates
        sc["half_logdet_field"] = field_half_logdet(prob.velocity.dt_k, field_sigma, opt.field_tau)
        sc["log_z"] += sc["half_logdet_field"]
    sc["field_sigma"] = None if field_sigma is None else [float(x) for x in np.broadcast_to(field_sigma, (3,))]
    return sc


def select_and_solve(solve_round, vel_state: dict, opt, state: tuple, K: int, history: list,
                     field_state: dict, gyro):
    """The ML loop's final solve with σ_p chosen among opt.position_select by (J2), then (with
    opt.position_select_field) the field's cross-axis σ_d,y among those candidates at that σ_p. solve_round:
    ml.calibrate's closure; state: (bias, noise, nRk, θ, values) of the converged rounds; field_state: the
    closure's {"sigma": σ_d} (set to the choice). Each candidate solves from the same state (vel_state restored in
    between); the "off" candidate (σ ≥ OFF_SIGMA) is the plain final solve (no position state, scored as the
    σ → ∞ limit of (J2)), so that "off" winning with the configured field gives exactly the defaults' result.
    gyro: the loop's GyroMapState (a round's solve folds Ê into it): restored before every candidate and set to
    the chosen one's. Notes the scores in history[-1]["position_select"]."""
    bias, noise, nRk, theta, values0 = state
    restore = _snapshot(vel_state, gyro)
    scores, solved = [], []

    def run(sigma, field_sigma):
        restore()
        vel_state["pos_sigma"] = sigma
        field_state["sigma"] = field_sigma
        # a copy: build_problem inserts the position keys into the Values it is given
        start = None if values0 is None else gtsam.Values(values0)
        out = solve_round(bias, noise, nRk, theta, final=True, values0=start)
        try:
            sc = _score(out[1], out[2], sigma, opt, K, field_sigma)
        except RuntimeError:               # an indeterminate elimination: the candidate is not scored
            return
        sc["lm_iterations"] = int(out[3].iterations)
        scores.append(sc)
        solved.append((sc, out, dict(vel_state), field_sigma, (gyro.E.copy(), gyro.step)))

    for sigma in opt.position_select:
        run(None if float(sigma) >= OFF_SIGMA else float(sigma), opt.field_sigma)
        if opt.position_select_stop and len(scores) >= 2 and scores[-1]["log_z"] < scores[-2]["log_z"]:
            break                          # the evidence dropped: ln Z(σ_p) taken as unimodal (CPU, task J2)
    if not scores:
        raise RuntimeError("position_select: no candidate could be scored")
    pick = choose(scores, EVIDENCE_MARGIN)
    if opt.position_select_field and opt.field_sigma is not None and not opt.position_select_field_rounds:
        sig = np.broadcast_to(np.asarray(opt.field_sigma, float), (3,))
        p_sigma = None if pick["sigma_p"] >= OFF_SIGMA else pick["sigma_p"]
        n0 = len(scores)
        for sy in opt.position_select_field:
            if float(sy) != float(sig[1]):
                run(p_sigma, (float(sig[0]), float(sy), float(sig[2])))
        best = max(scores[n0:] + [pick], key=lambda s: s["log_z"])
        pick = best if best["log_z"] >= pick["log_z"] + EVIDENCE_MARGIN else pick
    if history:
        history[-1]["position_select"] = {"scores": scores, "chosen": pick["sigma_p"],
                                          "field_sigma": pick["field_sigma"]}
    sc, out, st, field_sigma, g = next(x for x in solved if x[0] is pick)
    vel_state.clear(); vel_state.update(st)
    field_state["sigma"] = field_sigma
    gyro.E, gyro.step = g
    return out


def final_with_selection(solve_round, ml_rounds, vel_state: dict, opt, state: tuple, K: int, every: int,
                         history: list, field_state: dict, gyro, round_solver):
    """ml.calibrate's final step with opt.position_select: returns (pre, prob, values, info) of the final solve and
    (bias, noise, nRk, θ, converged). Without opt.position_select_rounds the candidates are full final solves and
    the chosen one is returned. With it the candidates are solved as an ML round is (thinned magnetometer, the
    rounds' solver), and a chosen bound runs the ML rounds again under it (noise levels, bias, windows
    re-estimated bounded) before the final solve; "off" gives exactly the defaults' final solve."""
    from imugraph import keys
    from imugraph.graphs.solver import keyframe_rotations

    bias, noise, nRk, theta, values0, converged = state
    if not opt.position_select_rounds:
        out = select_and_solve(solve_round, vel_state, opt, (bias, noise, nRk, theta, values0), K, history,
                               field_state, gyro)
        return out, (bias, noise, nRk, theta, converged)
    restore = _snapshot(vel_state, gyro)

    solver = None                              # position_select_max_iter: the candidates' LM iterations capped
    if opt.position_select_max_iter:
        solver = replace(round_solver, max_iterations=int(opt.position_select_max_iter))

    def candidate_solve(*args, **kw):          # position_select_thin: the candidates' magnetometer thinned further
        return solve_round(*args, **dict(kw, final=False, every=every * max(1, int(opt.position_select_thin)),
                                         solver=solver))

    _, _, values, _ = select_and_solve(candidate_solve, vel_state, opt, (bias, noise, nRk, theta, values0), K,
                                       history, field_state, gyro)
    if vel_state.get("pos_sigma") is None:     # "off": the defaults' state and final solve
        restore()                              # the ML rounds' state and Ê, not a thinned candidate's
        return solve_round(bias, noise, nRk, theta, final=True, values0=values0), (bias, noise, nRk, theta,
                                                                                   converged)
    bias, noise, nRk, theta, values, converged = ml_rounds(bias, noise, keyframe_rotations(values, K),
                                                           values.atVector(keys.CALIB), values)
    if opt.position_select_field_rounds and opt.position_select_field and opt.field_sigma is not None:
        bias, noise, nRk, theta, values, converged = field_after_rounds(
            candidate_solve, ml_rounds, vel_state, opt, (bias, noise, nRk, theta, values, converged), K, history,
            field_state, gyro)
    return solve_round(bias, noise, nRk, theta, final=True, values0=values), (bias, noise, nRk, theta, converged)


def field_after_rounds(candidate_solve, ml_rounds, vel_state: dict, opt, state: tuple, K: int, history: list,
                       field_state: dict, gyro):
    """Options.position_select_field_rounds: the cross-field σ_d,y chosen under a chosen bound, at the noise levels
    the ML rounds reached UNDER that bound (one alternation of a coordinate ascent: σ_d,y by (J2) at fixed noise,
    so the measurement normalisers cancel between candidates; then the noise re-estimated at the chosen σ_d,y,
    whose dof charge in the Σm re-estimate (ml.py, field_dof) it sets). Candidates above field_sigma's σ_y in
    increasing order, each a thinned round solve from the same state, stopping when ln Z drops; a candidate
    replaces the configured σ_y only with ln B ≥ EVIDENCE_MARGIN, and then the ML rounds run again with it.
    Returns the (bias, noise, nRk, θ, values, converged) for the final solve; notes the scores in history."""
    bias, noise, nRk, theta, values, converged = state
    sig = np.broadcast_to(np.asarray(opt.field_sigma, float), (3,))
    p_sigma = vel_state.get("pos_sigma")
    restore = _snapshot(vel_state, gyro)
    scores = []

    def run(sy):
        restore()
        fs = (float(sig[0]), float(sy), float(sig[2]))
        field_state["sigma"] = fs
        out = candidate_solve(bias, noise, nRk, theta, values0=gtsam.Values(values))
        try:
            scores.append(_score(out[1], out[2], p_sigma, opt, K, fs))
        except RuntimeError:               # an indeterminate elimination: not scored
            return False
        return True

    ok = run(sig[1])
    for sy in sorted(float(c) for c in opt.position_select_field if float(c) > float(sig[1])):
        if not ok or not run(sy) or scores[-1]["log_z"] < scores[-2]["log_z"]:
            break
    restore()
    field_state["sigma"] = opt.field_sigma
    pick = max(scores[1:], key=lambda s: s["log_z"]) if len(scores) > 1 else None
    chosen = pick is not None and ok and pick["log_z"] >= scores[0]["log_z"] + EVIDENCE_MARGIN
    if history:
        history[-1]["position_select_field"] = {"scores": scores, "chosen": pick["field_sigma"] if chosen else
                                                [float(x) for x in sig]}
    if not chosen:
        return bias, noise, nRk, theta, values, converged
    field_state["sigma"] = tuple(pick["field_sigma"])
    return ml_rounds(bias, noise, nRk, theta, values)
