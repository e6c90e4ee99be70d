"""Gyroscope scale factor and axis misalignment E, estimated jointly with the orientations.

Model: the corrected rate is ω = (I + E)·b_gyr − b (E: 3×3, small; e = vec E row-major). The ML loop
preintegrates the gyro corrected by its current Ê; within a solve, a change δe moves every preintegrated
rotation to first order as (same recursion as the bias Jacobian, Forster et al. 2017 eq. 44, with the
rate error δω_j = δE·b_gyr,j = W_j δe, W_j = I₃ ⊗ b_gyr,jᵀ):

    ΔR_k(δb, δe) ≈ ΔR_k · Exp(∂ΔR_k/∂b · δb + ∂ΔR_k/∂e · δe),
    ∂ΔR_k/∂e = ΔR_kᵀ Σ_j kRb_j Exp(θ_j) J_r(θ_j) Δt_j W_j      (θ_j = (ω_j − b̂) Δt_j; the bias Jacobian is
                                                                 the same sum with −I in place of W_j)

So a change of E acts on interval k exactly like a bias change β_k − b = C_k δe, C_k = (∂ΔR_k/∂b)⁻¹ ∂ΔR_k/∂e.
The graph gives each gyro factor its own bias key β_k tied to the segment bias and E by the linear
constraint β_k = b_s(k) + C_k e (σ_c tiny): the C++ AHRSFactor stays, and E is estimated jointly
(graphs/gyro_map_block.py), not by alternation (which converged at ~0.8 per round on BROAD).

Why (BROAD, measured): fitting ω_opt = M·ω_meas against the optical orientation on the slow rotation
trials gives M − I of 0.2–0.7 % (trial 04: M_zz = 1.0031, M_zy = −0.0070) with 7–11 net turns about the
vertical: 8–12° of heading the gyro gets wrong. A strongly weighted magnetometer hides it by bending the
gyro bias (segments spanning 0.9 °/s on trial 01, against ≈ 0.07 °/s from the optical fit). Correcting the
gyro with the optical M: heading RMS 1.34 → 0.94° (01), 1.15 → 0.38° (04).

Safety (measured on BROAD, benchmarks/b5_gyro_map_trace.py): estimated from every interval, E ran away on fast trials (16: +7 % per
ML round to +40 %, 16.8°; κ = 0 changes nothing; with the accelerometer as gravity-plus-noise −88 % in
round 1): E's regressor is the rate, which correlates with the unmodelled linear/centripetal acceleration
of fast motion, and E soaked it up. So (1) only intervals whose specific force stays within acc_tol of g
inform E (clean_intervals: 16 → 0.97°, 06 → 0.82°, still worse than without E), and (2) a coverage gate:
E is estimated only when those intervals hold enough rotation (clean_turns; BROAD 01/02/04/24 have
20–29 turns, 06/07 11/9, translation trials < 8), else E stays 0.

Why the gates are physical, not fitted (measured with benchmarks/b6_gyro_coverage.py and
b5_gyro_map_trace.py):
  * clean intervals: E's regressor is ω; the unmodelled part of the specific force (centripetal ω²r,
    tangential ω̇r, velocity-model errors) grows with the same motion, so only where |b_acc| ≈ g is the
    accelerometer a clean tilt reference for E to be checked against;
  * coverage: column i of E is excited only by rotation about body axis i, and a rate error ε over n turns
    is 2πnε of rotation — the signal grows with turns while the orientation references' errors do not. The
    trials that pass (01/02/04/24: 20–29 clean turns) have ≥ 7 turns about every axis; the next ones
    (32: 14.9, 06: 10.9, 07: 9.6) are below 15;
  * settling: a jointly determined E converges geometrically fast across ML rounds (step ratio 0.12–0.39 on
    01/02/04), since a round only updates noise levels and the frozen intra-interval quantities; a ratio
    > gyro_map_max_contraction means E follows what the rounds freeze. It also catches the trials the
    coverage gate keeps out: with that gate lowered (9 or 0 turns), 06, 07, 16, 21, 30 and 32 all fail the
    settling gate (ratios 0.62–6.9, E up to 22 % on 21) and get the plain model's result.
Fallback (calibration.ml): E is estimated from the first ML round; if the settling gate fails (checked
after every round), Ê is reset to 0 and the plain model's ML rounds run from the kept starting state
(default, gyro_map_fallback="restart"): the result is then exactly the run without E. Option "warm"
continues them from the E rounds' state (keyframe rotations, bias, θ, noise levels, τ, velocities,
windows) — BROAD 24 against gyro_map=False: orientation ≤ 1.3e-4° apart, θ within 0.0014 σ — but its
discrete decisions can differ: on a simulated attached magnet (tests/test_disturbance.py) the warm rounds
start from the E rounds' inflated σ_mag and end with the window "not modelled", so it is not the default.

Cost (`benchmarks/b6_profile.py TRIAL --opt gyro_map=… --repeat 2 --top 0`, CPU, one BLAS thread, shared
machine): only the trials that pass the coverage gate pay (the gate itself is a few ms). Where E settles, the
extra is one or two ML rounds (E's steps shrink 0.12–0.39 per round down to gyro_map_tol: 3 rounds on 02/04,
4 on 01, against 2 without E) and the β_k/e keys in each round's graph (e joins every clique's separator):
04 2.29 → 2.60 s. Where it does not settle (BROAD 24), the two rounds with E were thrown away and the plain
rounds run in full: 2.35 → 4.26 s (the default); continued warm the plain rounds take 3 LM iterations instead of 7
(LM total 19 → 15, against 12 without E): 3.00 s, same machine 1.94 s without E. map_jacobian reads
kRb_j Exp(θ_j) J_r(θ_j)Δt_j formed inside the preintegration's recursion (Preintegration.steps).
"""

from __future__ import annotations

import numpy as np

from imugraph.factors.gyro import Preintegration, exp_and_right_jacobian, preintegrate


def corrected_rate(b_gyr: np.ndarray, E: np.ndarray) -> np.ndarray:
    """(I + E)·b_gyr (N, 3): the gyro with its scale/misalignment E removed (the model's ω before the bias)."""
    return b_gyr + b_gyr @ np.asarray(E, float).T


def map_jacobian(b_gyr: np.ndarray, dt: np.ndarray, pre: Preintegration, bias_rows: np.ndarray) -> np.ndarray:
    """∂Log(ΔR_k)/∂e (K−1, 3, 9) of each keyframe interval (formula in the module docstring).

    Args:
        b_gyr: (N, 3) the gyro as preintegrated (already corrected by Ê), rad/s; dt: (N,) steps, s;
        pre: the preintegration of b_gyr; bias_rows: (N, 3) bias used for each sample.
    """
    if pre.steps is not None:                                       # kept by preintegrate(keep_steps=True):
        P = pre.steps                                               # kRb_j Exp(θ_j) J_r(θ_j) Δt_j
    else:
        exp, jr = exp_and_right_jacobian((b_gyr - bias_rows) * dt[:, None])
        P = pre.kRb @ exp @ jr * dt[:, None, None]
    PW = (P[:, :, :, None] * b_gyr[:, None, None, :]).reshape(-1, 3, 9)   # · (I₃ ⊗ ωᵀ)
    K = len(pre.kf_samples)
    S = np.zeros((K, 3, 9))
    first = np.r_[0, np.flatnonzero(np.diff(pre.sample_kf)) + 1]         # samples are grouped by keyframe
    S[pre.sample_kf[first]] = np.add.reduceat(PW, first, axis=0)
    return np.transpose(pre.delta_R, (0, 2, 1)) @ S[:-1]


def map_jacobian_numeric(b_gyr: np.ndarray, dt: np.ndarray, pre: Preintegration, bias_rows: np.ndarray,
                         eps: float = 1e-6) -> np.ndarray:
    """Central differences of the preintegration w.r.t. e (reference for tests)."""
    from scipy.spatial.transform import Rotation

    out = np.zeros((len(pre.delta_R), 3, 9))
    zero = np.zeros(3)
    for i in range(9):
        Em = np.zeros(9)
        Em[i] = eps
        Em = Em.reshape(3, 3)
        plus = preintegrate(b_gyr + b_gyr @ Em.T, dt, pre.kf_samples, pre.sample_kf, bias_rows, zero).delta_R
        minus = preintegrate(b_gyr - b_gyr @ Em.T, dt, pre.kf_samples, pre.sample_kf, bias_rows, zero).delta_R
        out[:, :, i] = Rotation.from_matrix(np.einsum("kji,kjl->kil", minus, plus)).as_rotvec() / (2 * eps)
    return out


def equivalent_bias_map(pre: Preintegration, dR_de: np.ndarray) -> np.ndarray:
    """C_k = (∂ΔR_k/∂b)⁻¹ ∂ΔR_k/∂e (K−1, 3, 9): the bias change that moves ΔR_k as δe does."""
    return np.linalg.solve(pre.dR_db, dR_de)


def clean_intervals(b_acc: np.ndarray, g: float, sample_kf: np.ndarray, n_intervals: int,
                    acc_tol: float) -> np.ndarray:
    """(K−1,) bool: keyframe intervals whose every sample has | |b_acc| − g | < acc_tol (m/s²).

    Why: on fast trials E ran away (BROAD 16: Ê_xx, Ê_yy +7 % per ML round, to +40 %; with the
    accelerometer as gravity-plus-noise −88 % in one round) — not κ (same with κ = 0), not the
    linearisation (steps did not shrink). E's regressor is the rate ω, and fast motion brings specific
    forces far from g (linear and centripetal acceleration) that the velocity model only partly explains:
    E absorbed those residuals. Only intervals where the accelerometer sees gravity alone inform E.
    """
    dev = np.abs(np.linalg.norm(b_acc, axis=1) - g)
    dev = np.where(np.isfinite(dev), dev, np.inf)
    worst = np.zeros(n_intervals + 1)
    np.maximum.at(worst, sample_kf, dev)
    return worst[:n_intervals] < acc_tol


def clean_turns(b_gyr: np.ndarray, dt: np.ndarray, sample_kf: np.ndarray, clean: np.ndarray) -> float:
    """Rotation (full turns, ∫|ω|dt / 2π) inside the clean intervals: E's coverage gate.

    A rate error of ε over n turns is 2πnε of rotation; with few clean turns E is not determined by the
    gyro/gravity data and stays 0 (BROAD 15/16: 0.3/0.6 clean turns; 01/04: 26/20).
    """
    ok = np.r_[clean, False][sample_kf]
    return float(np.sum(np.linalg.norm(b_gyr[ok], axis=1) * dt[ok]) / (2 * np.pi))


def coverage_gate(session, g: float, sample_kf: np.ndarray, n_intervals: int, opt) -> tuple[dict, np.ndarray]:
    """The coverage gate of calibration.ml: ({"estimated", "clean_turns", "clean_fraction"}, clean mask).

    E is estimated only when the intervals where the accelerometer sees gravity alone (clean_intervals,
    all intervals when opt.gyro_map_acc_tol is None) hold at least opt.gyro_map_min_turns turns.
    session.meta["gyro_map_exclude"] ((N,) bool, optional): intervals holding such a sample never inform E (the
    held-out blocks of calibration/gyro_map_select.py; GyroMapState also drops their gyro from the E rounds)."""
    clean = (np.ones(n_intervals, bool) if opt.gyro_map_acc_tol is None else
             clean_intervals(session.acc, g, sample_kf, n_intervals, opt.gyro_map_acc_tol))
    held = excluded_intervals(session.meta.get("gyro_map_exclude"), sample_kf, n_intervals)
    if held is not None:
        clean = clean & ~held
    turns = clean_turns(session.gyr, session.dt, sample_kf, clean)
    return ({"estimated": turns >= opt.gyro_map_min_turns, "clean_turns": turns,
             "clean_fraction": float(clean.mean()) if len(clean) else 0.0}, clean)


HELD_COV_SCALE = 1e10    # gyro covariance factor of a held-out interval in the E rounds: its gyro carries no weight


def excluded_intervals(exclude: np.ndarray | None, sample_kf: np.ndarray, n_intervals: int) -> np.ndarray | None:
    """(K−1,) bool: keyframe intervals holding an excluded sample (None when exclude is None)."""
    if exclude is None:
        return None
    hit = np.bincount(sample_kf, weights=np.asarray(exclude, float), minlength=n_intervals + 1)
    return hit[:n_intervals] > 0


class GyroMapState:
    """The Ê applied to the gyro between the rounds of the ML loop (calibration/ml.py), and its last step.

    clean: (K−1,) intervals allowed to inform E (clean_intervals); the others keep C_k = 0, i.e. their
    gyro factors see Ê (applied to every sample by the preintegration) but do not pull on it.
    exclude: (N,) samples held out (gyro_map_select; None: none). In the E rounds their intervals' gyro factors
    get HELD_COV_SCALE × their covariance and their samples are not corrected by Ê: E is then fitted from the
    other intervals' gyro alone. (Keeping those gyro factors, with Ê applied but C_k = 0, made the rounds
    diverge when half the intervals were held out — BROAD 01, 2 folds of 4 s: step ratio 1.46 — and with them
    raw, E took up their rate error too: Ê ≈ 2 × the whole recording's.) The final solve uses every gyro factor.
    """

    def __init__(self, sigma_e: float, clean: np.ndarray | None = None, exclude: np.ndarray | None = None):
        self.E = np.zeros((3, 3))
        self.step = 0.0
        self.sigma_e = sigma_e
        self.clean = clean
        self.exclude = None if exclude is None else np.asarray(exclude, bool)

    def corrected(self, b_gyr: np.ndarray) -> np.ndarray:
        """(I + Ê) b_gyr (b_gyr itself on the excluded samples)."""
        if self.exclude is None:
            return corrected_rate(b_gyr, self.E)
        return np.where(self.exclude[:, None], b_gyr, corrected_rate(b_gyr, self.E))

    def model(self, g_c: np.ndarray, dt: np.ndarray, pre: Preintegration, bias_rows: np.ndarray):
        """The graph's GyroMapModel at this preintegration (g_c: the corrected gyro it integrated)."""
        from imugraph.graphs.single_imu import GyroMapModel

        C = equivalent_bias_map(pre, map_jacobian(g_c, dt, pre, bias_rows))
        if self.clean is not None:
            C = np.where(self.clean[:, None, None], C, 0.0)
        held = excluded_intervals(self.exclude, pre.sample_kf, len(pre.delta_R))
        if held is not None:              # this round's gyro factors of the held-out intervals: no weight
            pre.cov[held] *= HELD_COV_SCALE
        return GyroMapModel(C, self.E.ravel(), self.sigma_e)

    def fold(self, values) -> None:
        """Ê ← Ê + δE from a solution (the next preintegration applies it; the graph restarts at δE = 0)."""
        from imugraph.graphs.gyro_map_block import E_KEY

        d_e = values.atVector(E_KEY)
        self.E = self.E + d_e.reshape(3, 3)
        self.step = float(np.max(np.abs(d_e)))
