"""The velocity chain of the single-IMU graph as one vectorised block (see imugraph.factors.velocity).

The state of keyframe k is s_k = v_k (3) or, with an accelerometer bias, s_k = (v_k, b_k) (6), one key,
so that every interval is a three-key factor (GTSAM's Python JacobianFactor takes at most three keys).
Per interval k one JacobianFactor on (R_k, s_k, s_{k+1}) stacks the accelerometer increment
(robust-weighted), the Gauss–Markov prior and, with a bias, its random walk; one more holds s_0:

    [ w^½ J_R/σ_e   w^½ [−I  R_k B_k]/σ_e   w^½ [I  0]/σ_e ] [ξ_k   ]     [ −w^½ e_k/σ_e            ]
    [   0               [−φ_k I  0]/σ_w         [I  0]/σ_w ] [δs_k  ]  =  [ −(v_{k+1} − φ_k v_k)/σ_w ]
    [   0               [0  −I]/σ_rw            [0  I]/σ_rw] [δs_k+1]     [ −(b_{k+1} − b_k)/σ_rw    ]

With a second-order (AR(2)) velocity process (`ar2` = (a_1, a_2, q), imugraph.factors.velocity) the
Gauss–Markov rows carry only the chain's stationary start — v_0 ~ N(0, γ_0) in the prior, v_1 | v_0 in
interval 0's rows, zero rows elsewhere — and one more factor per k = 1 … K−2 on (s_{k−1}, s_k, s_{k+1}):

    [ −a_2 I   −a_1 I   I ] / √q · [δv_{k−1}; δv_k; δv_{k+1}] = −(v_{k+1} − a_1 v_k − a_2 v_{k−1}) / √q

The zero rows are left out of the interval factors. The AR(2) terms are linear in the velocities, so
`single_imu.build_problem` puts them into the nonlinear graph once per solve as C++ LinearContainerFactors
(`ar2_graph`; GTSAM re-linearises them exactly), instead of K Python-built factors per LM iteration.

A bounded position (`position` = (σ_p, τ_p), Options.position_sigma; H11): a velocity process alone bounds the
velocity but not its integral, and on the BROAD rotation trials the smoothed velocities integrate to 5–19 m of
travel where the optical position spans 0.5 m (benchmarks/h11_slow_drift.py): a slow tilt error ε leaks g·ε
into the horizontal specific force and the chain carries it as a phantom velocity (ė_v,y = −g ε_x). The sensor
stays within reach, so keyframe positions p_k (nav frame, m; key `pos_key`) integrate the velocities
(Euler: its error against the true position, Σ(v_{k+1} − v_k)Δt/2, telescopes and stays ≤ |v|Δt/2) and get
a stationary Gauss–Markov prior like the field perturbation's:

    (p_{k+1} − p_k − v_k Δt_k) / σ_kin = 0 ± 1,    p_0 ~ N(0, σ_p² I),    p_{k+1} = φ_k p_k + w_k,
    φ_k = exp(−Δt_k/τ_p),   w_k ~ N(0, σ_p² (1 − φ_k²) I)                                      (P1)

A tilt error ε held for T seconds moves the position by ½ g ε T² (0.1° for 10 s: 8.6 m), so even a
room-sized σ_p pins the slow tilt. All terms are linear: C++ factors added once per solve (`position_graph`).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from imugraph import keys
from imugraph.factors.robust import QUADRATIC, Kernel
from imugraph.factors.velocity import ar2_residuals, ar2_stationary, gauss_markov_axes, velocity_model
from imugraph.graphs.solver import keyframe_rotations, keyframe_vectors, state_keys


POSITION_KIN_SIGMA = 1e-3      # m: σ_kin of (P1), the Euler step held nearly exact (its error is bounded anyway)


def pos_key(k: int) -> int:
    """Key of keyframe k's position p_k (Vector3, nav frame, m; Options.position_sigma)."""
    return gtsam.symbol("p", int(k))


def initial_positions(v: np.ndarray, dt_k: np.ndarray) -> np.ndarray:
    """(K, 3) Euler-integrated positions of velocities v (K, ≥3) with p_0 = 0, the start of the p_k keys."""
    p = np.zeros((len(v), 3))
    p[1:] = np.cumsum(np.asarray(v, float)[:-1, :3] * np.asarray(dt_k, float)[:, None], axis=0)
    return p


@dataclass
class VelocityBlock:
    """Accelerometer increments Δv_k (K−1, 3) with error std (K−1,), interval lengths, and the priors.

    B: (K−1, 3, 3) bias integrals (None: no accelerometer bias state); bias_sigma0: prior std of b_0,
    m/s²; bias_rw: random-walk density of the bias, m/s²/√s.
    """

    dv: np.ndarray
    sigma_dv: np.ndarray
    dt_k: np.ndarray
    g: float
    sigma_v: float | np.ndarray = 0.5     # m/s, scalar or (3,) per nav axis (x, y, z)
    tau_v: float | np.ndarray = 2.0       # s, scalar or (3,)
    kernel: Kernel = QUADRATIC
    B: np.ndarray | None = None
    bias_sigma0: float = 0.3
    bias_rw: float = 1e-3
    rest: np.ndarray | None = None    # (K,) keyframes at rest: zero-velocity prior v_k ~ N(0, σ_rest²)
    sigma_rest: float = 0.02
    ar2: tuple | None = None          # (a_1, a_2, q): AR(2) velocity process replacing (σ_v, τ_v); K ≥ 3
    ar2_in_graph: bool = False        # the AR(2) terms are C++ factors of the graph (`ar2_graph`): then neither
    #                                   `cost` nor `linearize` evaluates them in Python
    position: tuple | None = None     # (σ_p m, τ_p s): keyframe positions with a bounded prior (P1), C++ factors
    #                                   of the graph (`position_graph`); None: no position state
    fixed_weights: np.ndarray | None = None   # (K−1,) robust weights of the increments held for a whole solve
    #   (the ML rounds re-weight between solves); None: re-weighted at every linearisation (IRLS). Set with a
    #   position state: its long-range coupling made the per-iteration re-weighting creep (BROAD 01, position_sigma
    #   1.0, benchmarks/h11_position.py: 5.2 s CPU per-iteration, 1.7 s held, 0.707° both)

    @property
    def n_keyframes(self) -> int:
        return len(self.dv) + 1

    @property
    def state_dim(self) -> int:
        return 3 if self.B is None else 6

    def _state(self, values: gtsam.Values):
        K = self.n_keyframes
        return keyframe_rotations(values, K), keyframe_vectors(values, keys.vel, K)

    def terms(self, nRk: np.ndarray, s: np.ndarray):
        """Whitened increment residuals r (K−1, 3), J_R, robust weights, GM and bias-walk residuals."""
        v = s[:, :3]
        b = None if self.B is None else s[:, 3:]
        e, J_R = velocity_model(nRk, v, self.dv, self.dt_k, self.g, b, self.B)
        r = e / self.sigma_dv[:, None]
        w = self.kernel.weight(np.linalg.norm(r, axis=1)) if self.fixed_weights is None else self.fixed_weights
        phi, sigma_w = gauss_markov_axes(self.dt_k, self.sigma_v, self.tau_v)      # (K−1, 3) each
        if self.ar2 is not None:       # only v_1 | v_0 here (σ_w = ∞: zero rows); the rest: `_ar2_factors`
            gamma0, rho1 = ar2_stationary(*self.ar2)
            phi, sigma_w = np.zeros_like(phi), np.full_like(sigma_w, np.inf)
            phi[0], sigma_w[0] = rho1, np.sqrt(gamma0 * (1.0 - rho1**2))
        gm = (v[1:] - phi * v[:-1]) / sigma_w
        walk = None if b is None else (b[1:] - b[:-1]) / self._sigma_rw()[:, None]
        return r, J_R, w, phi, sigma_w, gm, walk

    def _sigma_rw(self) -> np.ndarray:
        return np.maximum(self.bias_rw, 1e-9) * np.sqrt(self.dt_k)

    def _prior_sigma(self) -> np.ndarray:
        sigma0 = self.sigma_v if self.ar2 is None else np.sqrt(ar2_stationary(*self.ar2)[0])
        return np.r_[np.broadcast_to(np.asarray(sigma0, float), (3,)),
                     np.full(self.state_dim - 3, self.bias_sigma0)]

    def cost_at(self, nRk: np.ndarray, s: np.ndarray, with_ar2: bool = True) -> float:
        """The block's cost at orientations nRk (K, 3, 3) and states s (K, d); with_ar2=False leaves out the
        AR(2) terms (when they are in the graph: `ar2_graph`)."""
        r, _, w, _, _, gm, walk = self.terms(nRk, s)
        if self.fixed_weights is None:
            total = self.kernel.rho(np.linalg.norm(r, axis=1)).sum() + 0.5 * np.sum(gm**2)
        else:                                  # held weights: the weighted quadratic that `linearize` describes
            total = 0.5 * np.sum(w * np.sum(r**2, axis=1)) + 0.5 * np.sum(gm**2)
        total += 0.5 * np.sum((s[0] / self._prior_sigma()) ** 2)
        if walk is not None:
            total += 0.5 * np.sum(walk**2)
        if self.rest is not None:
            total += 0.5 * np.sum((s[self.rest, :3] / self.sigma_rest) ** 2)
        if self.ar2 is not None and with_ar2:
            total += 0.5 * np.sum(ar2_residuals(s[:, :3], *self.ar2)[2:] ** 2)
        return float(total)

    def cost(self, values: gtsam.Values) -> float:
        return self.cost_at(*self._state(values), with_ar2=not self.ar2_in_graph)

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        nRk, s = self._state(values)
        r, J_R, w, phi, sigma_w, gm, walk = self.terms(nRk, s)
        d = self.state_dim
        n = len(r)
        rows = 6 if walk is None else 9
        sw = (np.sqrt(w) / self.sigma_dv)[:, None, None]      # (K−1,) row scale of the increment rows
        eye = np.eye(3)
        gfg = gtsam.GaussianFactorGraph()
        ps = self._prior_sigma()
        gfg.push_back(gtsam.JacobianFactor(keys.vel(0), np.diag(1.0 / ps), -s[0] / ps,
                                           gtsam.noiseModel.Unit.Create(d)))
        # the stacked blocks of every interval at once (rows as in the module docstring)
        A_R = np.zeros((n, rows, 3)); A0 = np.zeros((n, rows, d)); A1 = np.zeros((n, rows, d))
        rhs = np.zeros((n, rows))
        A_R[:, :3] = J_R * sw
        A0[:, :3, :3] = -eye * sw; A1[:, :3, :3] = eye * sw
        A0[:, 3:6, :3] = -(phi / sigma_w)[:, :, None] * eye; A1[:, 3:6, :3] = (1.0 / sigma_w)[:, :, None] * eye
        rhs[:, :3] = -r * np.sqrt(w)[:, None]
        rhs[:, 3:6] = -gm
        if walk is not None:
            srw = self._sigma_rw()[:, None, None]
            A0[:, :3, 3:] = np.einsum("kij,kjl->kil", nRk[:-1], self.B) * sw
            A0[:, 6:9, 3:] = -eye / srw; A1[:, 6:9, 3:] = eye / srw
            rhs[:, 6:9] = -walk
        vk, rk = state_keys(keys.vel, n + 1), state_keys(keys.rot, n + 1)
        self._interval_factors(gfg, rk, vk, A_R, A0, A1, rhs)
        if self.rest is not None:
            A = np.zeros((3, d)); A[:, :3] = eye / self.sigma_rest
            unit3 = gtsam.noiseModel.Unit.Create(3)
            for k in np.flatnonzero(self.rest):
                gfg.push_back(gtsam.JacobianFactor(keys.vel(int(k)), A, -s[k, :3] / self.sigma_rest, unit3))
        if self.ar2 is not None and not self.ar2_in_graph:
            self._ar2_factors(gfg, s, vk)
        return gfg

    def _interval_factors(self, gfg: gtsam.GaussianFactorGraph, rk, vk, A_R, A0, A1, rhs) -> None:
        """One JacobianFactor per interval from the stacked rows (module docstring). With the AR(2) process the
        Gauss–Markov rows 3:6 of intervals k ≥ 1 are exactly zero (σ_w = ∞) and are left out (rows that add
        nothing to the normal equations, but cost their conversion and elimination)."""
        n, rows = rhs.shape
        k0 = 0
        if self.ar2 is not None and n > 1:
            gfg.push_back(gtsam.JacobianFactor(rk[0], A_R[0], vk[0], A0[0], vk[1], A1[0], rhs[0],
                                               gtsam.noiseModel.Unit.Create(rows)))
            keep = np.r_[0:3, 6:rows]
            A_R, A0, A1, rhs = A_R[:, keep], A0[:, keep], A1[:, keep], rhs[:, keep]
            k0 = 1
        unit = gtsam.noiseModel.Unit.Create(rhs.shape[1])
        push, JF = gfg.push_back, gtsam.JacobianFactor
        for k in range(k0, n):
            push(JF(rk[k], A_R[k], vk[k], A0[k], vk[k + 1], A1[k], rhs[k], unit))

    def ar2_graph(self) -> gtsam.NonlinearFactorGraph:
        """The AR(2) terms as C++ nonlinear factors for the graph itself (exact: they are linear in s):
        LinearContainerFactors of their Jacobians at s = 0, which GTSAM re-linearises (b = −A s) and evaluates
        without Python per iteration. The caller sets `ar2_in_graph` once they are in the graph."""
        K = self.n_keyframes
        vk = state_keys(keys.vel, K)
        gfg = gtsam.GaussianFactorGraph()
        self._ar2_factors(gfg, np.zeros((K, self.state_dim)), vk)
        zero = gtsam.Values()
        for key in vk:
            zero.insert(key, np.zeros(self.state_dim))
        return gtsam.LinearContainerFactor.ConvertLinearGraph(gfg, zero)

    def position_graph(self, sigma_kin: float = POSITION_KIN_SIGMA) -> gtsam.NonlinearFactorGraph:
        """The position terms (P1) as C++ nonlinear factors (exact: linear in p and v), as `ar2_graph`."""
        sigma_p, tau_p = self.position
        K, d = self.n_keyframes, self.state_dim
        vk, pk = state_keys(keys.vel, K), state_keys(pos_key, K)
        phi = np.exp(-self.dt_k / max(float(tau_p), 1e-9))
        sigma_w = float(sigma_p) * np.sqrt(np.maximum(1.0 - phi**2, 1e-12))
        gfg = gtsam.GaussianFactorGraph()
        eye, unit3 = np.eye(3), gtsam.noiseModel.Unit.Create(3)
        gfg.push_back(gtsam.JacobianFactor(pk[0], eye / float(sigma_p), np.zeros(3), unit3))
        for k in range(K - 1):
            A_v = np.zeros((3, d))
            A_v[:, :3] = -eye * self.dt_k[k] / sigma_kin
            gfg.push_back(gtsam.JacobianFactor(pk[k], -eye / sigma_kin, pk[k + 1], eye / sigma_kin, vk[k], A_v,
                                               np.zeros(3), unit3))
            gfg.push_back(gtsam.JacobianFactor(pk[k], -phi[k] * eye / sigma_w[k], pk[k + 1], eye / sigma_w[k],
                                               np.zeros(3), unit3))
        zero = gtsam.Values()
        for key in vk:
            zero.insert(key, np.zeros(d))
        for key in pk:
            zero.insert(key, np.zeros(3))
        return gtsam.LinearContainerFactor.ConvertLinearGraph(gfg, zero)

    def _ar2_factors(self, gfg: gtsam.GaussianFactorGraph, s: np.ndarray, vk: list) -> None:
        """The AR(2) terms k = 1 … K−2 (module docstring) as three-key JacobianFactors."""
        a1, a2, q = self.ar2
        r = ar2_residuals(s[:, :3], a1, a2, q)
        A = [np.zeros((3, self.state_dim)) for _ in range(3)]
        for block, c in zip(A, (-a2, -a1, 1.0)):
            block[:, :3] = c * np.eye(3) / np.sqrt(q)
        unit3 = gtsam.noiseModel.Unit.Create(3)
        for k in range(1, self.n_keyframes - 1):
            gfg.push_back(gtsam.JacobianFactor(vk[k - 1], A[0], vk[k], A[1], vk[k + 1], A[2], -r[k + 1], unit3))
