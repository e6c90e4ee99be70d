"""The velocity process (σ_v, τ_v) estimated by the stream itself at the end of the stream (StreamOptions.velocity_end).

The stream's bounded-velocity chain (stream.py `_close`; imugraph.factors.velocity) holds the START calibration's
first-order Gauss–Markov process,

    v_0 ~ N(0, σ_v² I),   v_{k+1} = φ_k v_k + w_k,   φ_k = exp(−Δt_k/τ_v),   w_k ~ N(0, σ_v² (1 − φ_k²) I)      (1)

while the batch re-estimates (σ_v, τ_v) on the whole trial inside its ML loop (calibration/velocity_process.py,
velocity_ar2.py: EM, Shumway & Stoffer 1982). A 30-s bootstrap says τ_v ≈ 0.2–2 s, the whole trial often 0.05 s
(BROAD 07, 30; docs/stream.md "Session 17, helper L": the batch's process fed to the stream closes 07 0.26 → 0.12°).
Here the same EM runs on the end-of-stream graph (full iSAM2 with history), as an end extension
(`StreamSmoother._end_extensions`, applied before the end Levenberg–Marquardt, stream_output.finish):

- E-step at the solved orientations (as the batch's: orientations, positions, gyro bias, gravity, d_k, θ held):
  the velocity part of the end graph is then linear. Linearising every non-process factor on a velocity key at
  the solution x (Huber weights at x) gives Λ_R (block-tridiagonal) and η = Σ Aᵀb; with the process's precision
  G(σ, τ) of (1) (tridiagonal per nav axis),

      (Λ_R + G) m = Λ_R x_v + η,    P_k,k, C_k = bands of (Λ_R + G)⁻¹                                         (2)

  (the posterior mean and covariance of the chain, per nav axis: the velocity rows of the ImuFactor are
  isotropic, R_iᵀ whitened by one σ_Δv; Takahashi's recursion, velocity_process.banded_inverse_bands);
- M-step: the batch's own, from the moments E v_k v_{k+l} = m_k m_{k+l} + Z_l (velocity_process.moments), bounds of
  the batch's "bounded" mode (process_bounds with the batch's configured Options().velocity_sigma, velocity_tau:
  σ_v ≥ 0.5 m/s, τ_v ≤ 2 s). Modes:
  "ar2_batch": the batch's default `estimate_velocity_process="bounded_ar2"` at the batch's keyframe
  spacing s·Δt (Options().keyframe_hz 5 Hz: s = 2 stream intervals), pooled over the s interleaved subsequences,

      v_{k+2s} = a_1 v_{k+s} + a_2 v_k + w_k,   w_k ~ N(0, q)     (velocity_ar2.fit_ar2 on lags 0, s, 2s)        (4)

  handed on as its first-order equivalent σ_v = √γ_0, τ_v = −sΔt/ln ρ_1 (velocity_ar2.update_ar2: what the batch's
  Calibration gives smooth_fixed); the E-step's prior is that first-order process (1), the one the graph holds;
  "ar2_batch_em": the same with (4) itself as the E-step's prior (s interleaved AR(2) chains, starts as (3); in the
  graph between the solves), i.e. EM of model (4); only the end graph gets the first-order equivalent (BROAD 36:
  τ_v 0.31 s, the batch's 0.315 s; "ar2_batch" 0.46 s);
  "ar2_batch_id" (recommended): "ar2_batch_em", kept unless both variance bounds decide it: the fitted innovation
  variance f(a)/N below the bounded mode's floor q_floor = σ_lo² (1 − φ_max²) (so q̂ = q_floor) and √γ_0 = σ_lo (within
  1 %); (a_1, a_2) then lie on the bounds' curve, where smooth and alternating processes fit alike (BROAD 06 and 07 give
  the same such fit, a root near −1; the batch's τ_v is 2.0 s on 06, 0.05 s on 07): the start's process is kept;
  "ar2": the AR(2) at the stream's own spacing, its E-step under the AR(2) prior

      v_0 ~ N(0, γ_0),  v_1 | v_0 ~ N(ρ_1 v_0, γ_0 (1 − ρ_1²)),  v_{k+1} = a_1 v_k + a_2 v_{k−1} + w_k           (3)

  (factors.velocity.ar2_residuals; 3-key linear factors in the graph between the solves), first-order equivalent at
  the end; the AR(2)'s ρ_1 at 0.1 s is not the batch's at 0.2 s (BROAD 30: τ 0.205 s vs the batch's 0.05 s);
  "gm": the first-order ML of velocity_process.fit_gauss_markov (BROAD 07: τ_v 2 s, the batch 0.05 s);
- E- and M-step alternate at the held orientations (no graph solve: eq. 2 is one banded solve, velocity_em) until
  the process moves < 1e-3 (log σ, τ; a_1, a_2, log q); then the process factors are REPLACED in the end graph (v_0's
  prior and every (v_k, v_{k+1}) linear factor: the only factors on exactly those keys) and the graph is re-solved;
  repeated until the process moves < Options().noise_tol (the batch's round tolerance) or `OUTER_MAX` solves.

Only the end-of-stream smoothed output changes (filtered output, fixed lag untouched). The result is in
`StreamSmoother.velocity_end_result` (σ̂_v, τ̂_v, start values, iterations, the last fit: a_1, a_2, q, f(a)/N, q_floor,
`identified`). Measured on BROAD: docs/stream.md, "Session 18, helper V".
"""

from __future__ import annotations

import time

import gtsam
import numpy as np
from scipy.linalg import solveh_banded

from imugraph import keys
from imugraph.calibration.velocity_ar2 import ar2_objective_terms, fit_ar2, lag_moments
from imugraph.calibration.velocity_process import (banded_inverse_bands, fit_gauss_markov, moments,
                                                   process_bounds)
from imugraph.factors.velocity import ar2_stationary, gauss_markov
from imugraph.graphs.cpp_velocity import gauss_markov_factors

MODES = ("off", "ar2", "gm", "ar2_batch", "ar2_batch_em", "ar2_batch_id")
OUTER_MAX = 4          # end-graph solves with a re-estimated process (the batch: one EM step per ML round)
INNER_MAX = 50         # EM steps at the held orientations
INNER_TOL = 1e-3       # |Δ ln σ|, |Δ ln τ| of an inner step
ID_MARGIN = 1.01       # "ar2_batch_id": √γ_0 above 1.01 σ_lo counts as off its bound
_V = ord("v")


def process_chain(graph: gtsam.NonlinearFactorGraph, K: int) -> tuple[list, list]:
    """(indices of the process factors of eq. 1 in `graph`, indices of the other factors on a velocity key): v_0's
    PriorFactorVector and the LinearContainerFactors on exactly (v_k, v_{k+1})."""
    proc, other = [], []
    v0 = keys.vel(0)
    for i in range(graph.size()):
        if not graph.exists(i):
            continue
        f = graph.at(i)
        ks = list(f.keys())
        if not any(gtsam.Symbol(k).chr() == _V for k in ks):
            continue
        if (len(ks) == 1 and ks[0] == v0 and isinstance(f, gtsam.PriorFactorVector)) or (
                len(ks) == 2 and isinstance(f, gtsam.LinearContainerFactor)
                and all(gtsam.Symbol(k).chr() == _V for k in ks)
                and gtsam.Symbol(ks[1]).index() == gtsam.Symbol(ks[0]).index() + 1):
            proc.append(i)
        else:
            other.append(i)
    return proc, other


def chain_information(graph, idx: list, x: gtsam.Values, K: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Eq. (2)'s Λ_R per nav axis in lower banded form (2, K, 3) and η (K, 3) from the factors `idx` linearised at
    x with every other variable held; also the largest within-block cross-axis term relative to the diagonal
    (dropped: ≈ 0 for the isotropic velocity rows)."""
    dims = x.dims()
    D = np.zeros((K, 3, 3))
    O = np.zeros((K, 3, 3))            # O[k] = Λ_{k+1, k}
    eta = np.zeros((K, 3))
    for i in idx:
        f = graph.at(i)
        ks = list(f.keys())
        H = f.linearize(x).augmentedInformation()
        starts = np.r_[0, np.cumsum([dims[k] for k in ks])]
        vel = [(int(gtsam.Symbol(k).index()), starts[j]) for j, k in enumerate(ks) if gtsam.Symbol(k).chr() == _V]
        for a, (ka, ca) in enumerate(vel):
            D[ka] += H[ca:ca + 3, ca:ca + 3]
            eta[ka] += H[ca:ca + 3, -1]
            for kb, cb in vel[a + 1:]:
                if kb == ka + 1:
                    O[ka] += H[cb:cb + 3, ca:ca + 3]
                elif kb == ka - 1:
                    O[kb] += H[ca:ca + 3, cb:cb + 3]
    diag = np.einsum("kii->ki", D)
    off = np.einsum("kii->ki", O)[:-1]
    cross = max(np.abs(D - diag[:, :, None] * np.eye(3)).max(), np.abs(O - np.einsum("kii->ki", O)[:, :, None]
                                                                          * np.eye(3)).max())
    ab = np.zeros((2, K, 3))
    ab[0], ab[1, :-1] = diag, off
    return ab, eta, float(cross / max(diag.max(), 1e-30))


def process_bands(proc: tuple, dt_k: np.ndarray, K: int) -> np.ndarray:
    """The process's precision per nav axis in lower banded form (3, K) (the same on every axis). ("gm", σ, τ), eq. (1):
    v_0's prior 1/σ², each step b_k = 1/σ_w,k² on [[φ_k², −φ_k], [−φ_k, 1]] (velocity_process.chain_bands);
    ("ar2", a_1, a_2, q), eq. (3): v_0 ~ N(0, γ_0), v_1 | v_0 ~ N(ρ_1 v_0, γ_0 (1 − ρ_1²)), then c cᵀ with
    c = (−a_2, −a_1, 1)/√q on (v_{k−1}, v_k, v_{k+1}), k = 1 … K−2 (factors.velocity.ar2_residuals)."""
    g = np.zeros((3, K))
    if proc[0] == "gm":
        sigma, tau = proc[1:]
        phi, sig_w = gauss_markov(dt_k, sigma, tau)
        b = 1.0 / sig_w**2
        g[0, 0] += 1.0 / sigma**2
        g[0, :-1] += b * phi**2
        g[0, 1:] += b
        g[1, :-1] = -b * phi
        return g
    a1, a2, q = proc[1:4]
    sp = proc[4] if len(proc) > 4 else 1                 # eq. (4)'s spacing: s interleaved chains
    if sp > 1:
        g = np.zeros((2 * sp + 1, K))
    gamma0, rho1 = ar2_stationary(a1, a2, q)
    b1 = 1.0 / (gamma0 * (1.0 - rho1**2))
    for j in range(min(sp, K)):                          # v_j ~ N(0, γ_0), v_{j+s} | v_j ~ N(ρ_1 v_j, γ_0 (1 − ρ_1²))
        g[0, j] += 1.0 / gamma0
        if j + sp < K:
            g[0, j] += b1 * rho1**2
            g[0, j + sp] += b1
            g[sp, j] += -b1 * rho1
    c, n = np.array([-a2, -a1, 1.0]) / np.sqrt(q), K - 2 * sp
    if n > 0:
        for i in range(3):
            g[0, i * sp:i * sp + n] += c[i] ** 2
        g[sp, 0:n] += c[0] * c[1]
        g[sp, sp:sp + n] += c[1] * c[2]
        g[2 * sp, 0:n] += c[0] * c[2]
    return g


def process_factors(proc: tuple, dt_k: np.ndarray) -> list:
    """The process as exact linear factors on the velocity keys: eq. (1) as _start/_close issue it
    (cpp_velocity.gauss_markov_factors), or eq. (3)'s rows as one 3-key linear factor each."""
    if proc[0] == "gm":
        return gauss_markov_factors(dt_k, proc[1], proc[2])
    a1, a2, q = proc[1:4]
    sp = proc[4] if len(proc) > 4 else 1
    gamma0, rho1 = ar2_stationary(a1, a2, q)
    zero3, eye = np.zeros(3), np.eye(3)
    s1, K = np.sqrt(gamma0 * (1.0 - rho1**2)), len(dt_k) + 1
    out = []
    for j in range(min(sp, K)):
        out.append(gtsam.PriorFactorVector(keys.vel(j), zero3, gtsam.noiseModel.Isotropic.Sigma(3, np.sqrt(gamma0))))
        if j + sp < K:
            out.append(_linear([(keys.vel(j), -rho1 / s1 * eye), (keys.vel(j + sp), eye / s1)]))
    sq = np.sqrt(q)
    for k in range(K - 2 * sp):
        out.append(_linear([(keys.vel(k), -a2 / sq * eye), (keys.vel(k + sp), -a1 / sq * eye),
                            (keys.vel(k + 2 * sp), eye / sq)]))
    return out


def _linear(blocks: list) -> gtsam.LinearContainerFactor:
    """Σ A_j x_j ~ N(0, I) on 3-vector keys, an exact linear factor (linearised at 0)."""
    args = [a for kA in blocks for a in kA]                # i1, A1, i2, A2[, i3, A3]
    jf = gtsam.JacobianFactor(*args, np.zeros(3), gtsam.noiseModel.Unit.Create(3))
    lin = gtsam.Values()
    for k, _ in blocks:
        lin.insert(k, np.zeros(3))
    return gtsam.LinearContainerFactor(jf, lin)


def e_step(ab_r: np.ndarray, eta: np.ndarray, x_v: np.ndarray, g: np.ndarray, bands: int = 3):
    """Eq. (2): posterior means m (K, 3) and the first `bands` (≥ 3) bands of the inverse Z (bands, K, 3) per axis."""
    K = len(x_v)
    m, Z = np.empty((K, 3)), np.empty((bands, K, 3))
    for i in range(3):
        ab = np.zeros((max(bands, len(g)), K))
        ab[:len(g)] = g
        ab[:2] += ab_r[:, :, i]
        lx = ab_r[0, :, i] * x_v[:, i]                   # Λ_R x_v, Λ_R tridiagonal (lower form)
        lx[:-1] += ab_r[1, :-1, i] * x_v[1:, i]
        lx[1:] += ab_r[1, :-1, i] * x_v[:-1, i]
        m[:, i] = solveh_banded(ab, lx + eta[:, i], lower=True)
        Z[:, :, i] = banded_inverse_bands(ab)[:bands]
    return m, Z


def m_step(mode: str, m: np.ndarray, Z: np.ndarray, dt_k: np.ndarray, bounds: tuple, spacing: int = 1,
           info: dict | None = None) -> tuple:
    """The batch's M-step (module docstring): ("gm", σ_v, τ_v) or ("ar2", a_1, a_2, q); with spacing s > 1 ("ar2_batch")
    the AR(2) at s keyframe intervals (the batch's keyframe spacing), eq. (4), returned as its first-order equivalent
    ("gm", √γ_0, −s Δt / ln ρ_1)."""
    sigma_b, tau_b = bounds
    if mode == "gm":
        s0, s1 = moments(m, Z[0], Z[1, :-1])
        return ("gm",) + fit_gauss_markov(s0, s1, dt_k, tau_b, sigma_b)
    K = len(m)
    dt = spacing * float(np.median(dt_k))
    if spacing == 1:
        syy, sxy, sxx = ar2_objective_terms(lag_moments(m, Z))   # velocity_ar2.update_ar2
    else:
        syy, sxy, sxx = _spaced_terms(m, Z, spacing)
    N, phi_max = 3 * (K - 2 * spacing), float(np.exp(-dt / tau_b[1]))
    proc = ("ar2",) + fit_ar2(syy, sxy, sxx, N, sigma_b, phi_max)
    if info is not None:             # is q̂ the data's innovation variance f(a)/N, or a bound (q_floor, σ_lo² γ-factor)?
        a = np.array(proc[1:3])
        info.update(ar2=list(proc[1:]), f_over_n=float((syy - 2 * a @ sxy + a @ sxx @ a) / N),
                    q_floor=float(sigma_b[0] ** 2 * (1.0 - phi_max**2)),
                    sigma_fit=float(np.sqrt(ar2_stationary(*proc[1:])[0])), sigma_lo=float(sigma_b[0]))
    if spacing == 1:
        return proc
    if mode in ("ar2_batch_em", "ar2_batch_id"):   # the AR(2) at the batch's spacing as the next E-step's prior (4)
        return proc + (spacing,)
    return ("gm",) + first_order(proc + (spacing,), dt_k, tau_b)


def _spaced_terms(m: np.ndarray, Z: np.ndarray, s: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Eq. (4): velocity_ar2.ar2_objective_terms of the AR(2) v_{k+2s} = a_1 v_{k+s} + a_2 v_k + w_k at s keyframe
    intervals, pooled over the s interleaved subsequences: lag moments E v_k v_{k+l} = m_k·m_{k+l} + Z_l (l = 0, s, 2s;
    summed over axes), k = 0 … K−1−2s."""
    K = len(m)
    n = K - 2 * s

    def E(lag, start):
        return float(np.sum(m[start:start + n] * m[start + lag:start + lag + n] + Z[lag, start:start + n]))

    syy = E(0, 2 * s)
    sxy = np.array([E(s, s), E(2 * s, 0)])
    sxx = np.array([[E(0, s), E(s, 0)], [E(s, 0), E(0, 0)]])
    return syy, sxy, sxx


def first_order(proc: tuple, dt_k: np.ndarray, tau_bounds: tuple) -> tuple[float, float]:
    """(σ_v, τ_v) of the stream's first-order chain: itself, or the AR(2)'s equivalent √γ_0, −Δt/ln ρ_1 (τ inside
    the bounds), as velocity_ar2.update_ar2 hands it to the Calibration."""
    if proc[0] == "gm":
        return float(proc[1]), float(proc[2])
    gamma0, rho1 = ar2_stationary(*proc[1:4])
    dt = (proc[4] if len(proc) > 4 else 1) * float(np.median(dt_k))
    return float(np.sqrt(gamma0)), float(np.clip(-dt / np.log(np.clip(rho1, 1e-9, 1 - 1e-9)), *tau_bounds))


def change(p: tuple, r: tuple) -> float:
    """Largest |Δ ln σ|, |Δ ln τ| (first order) or |Δa_1|, |Δa_2|, |Δ ln q| (AR(2), velocity_em); a change of kind: ∞."""
    if p[0] != r[0]:
        return np.inf
    if p[0] == "gm":
        return float(max(abs(np.log(r[1] / p[1])), abs(np.log(r[2] / p[2]))))
    return float(max(abs(r[1] - p[1]), abs(r[2] - p[2]), abs(np.log(r[3] / p[3]))))


class VelocityEnd:
    """The end extension (graph, values) -> (graph, values) of StreamOptions.velocity_end (module docstring)."""

    def __init__(self, sm, mode: str):
        if mode not in MODES[1:]:
            raise ValueError(f"StreamOptions.velocity_end: found {mode!r}, expected one of {MODES}")
        from imugraph.calibration.options import Options

        o = Options()
        self.sm, self.mode = sm, mode
        self.bounds = process_bounds("bounded", o.velocity_sigma, o.velocity_tau)   # the batch's bounds
        self.outer_tol = o.noise_tol
        self.batch_dt = 1.0 / o.keyframe_hz                # the batch's keyframe spacing ("ar2_batch")

    def __call__(self, graph, values):
        sm = self.sm
        start_cpu = time.thread_time()
        K = sm._k + 1
        dt_k = np.diff(np.asarray(sm._kf_t))[:K - 1]           # Δt_k = t_{k+1} − t_k, as _close's
        proc_idx, _ = process_chain(graph, K)
        res = {"mode": self.mode, "sigma_start": sm._sig_v, "tau_start": sm._tau_v, "sigma": sm._sig_v,
               "tau": sm._tau_v, "outer": 0, "inner": [], "path": []}
        sm.velocity_end_result = res
        if K < 5 or len(proc_idx) != K:                    # not the chain of eq. (1): leave the graph as it is
            res["skipped"] = f"{len(proc_idx)} process factors for {K} keyframes"
            return graph, values
        base = gtsam.NonlinearFactorGraph()
        skip = set(proc_idx)
        for i in range(graph.size()):
            if graph.exists(i) and i not in skip:
                base.add(graph.at(i))
        other_idx = process_chain(base, K)[1]
        proc = ("gm", sm._sig_v, sm._tau_v)                # the start calibration's, in the graph now
        x = values
        spacing = max(1, int(round(self.batch_dt / float(np.median(dt_k))))) if self.mode.startswith("ar2_batch") else 1
        bands = 2 * spacing + 1
        res["spacing"] = spacing
        for outer in range(OUTER_MAX):
            x = sm._final_lm(_with(base, process_factors(proc, dt_k)), x)
            ab_r, eta, cross = chain_information(base, other_idx, x, K)
            x_v = np.stack([x.atVector(keys.vel(k)) for k in range(K)])
            p_outer = proc
            for inner in range(1, INNER_MAX + 1):          # EM at the held orientations (velocity_em)
                new = m_step(self.mode, *e_step(ab_r, eta, x_v, process_bands(proc, dt_k, K), bands), dt_k,
                             self.bounds, spacing, res.setdefault("fit", {}))
                step, proc = change(proc, new), new
                if step < INNER_TOL:
                    break
            res["inner"].append(inner)
            res["path"].append(list(proc[1:]))
            res["cross_axis"] = cross
            res["outer"] = outer + 1
            if change(p_outer, proc) < self.outer_tol:
                break
        sigma, tau = first_order(proc, dt_k, self.bounds[1])
        fit = res.get("fit", {})
        # "ar2_batch_id": only a process the data identify — not both variance bounds active: the fitted innovation
        # variance f(a)/N below the bounded mode's floor (q̂ = q_floor) AND √γ_0 at σ_lo leave (a_1, a_2) on the bounds'
        # curve γ_0(a, q_floor) = σ_lo², where smooth (ρ_1 = φ_max) and alternating (a root near −1) processes fit alike
        # (BROAD 06 / 07: the same fit, the batch's τ_v 2.0 / 0.05 s); then the start's process is kept
        res["identified"] = bool(fit.get("f_over_n", np.inf) > fit.get("q_floor", 0.0)
                                 or fit.get("sigma_fit", np.inf) > ID_MARGIN * fit.get("sigma_lo", 0.0))
        if self.mode == "ar2_batch_id" and not res["identified"]:
            sigma, tau = res["sigma_start"], res["tau_start"]
        res.update(sigma=sigma, tau=tau, process=list(proc), cpu_s=time.thread_time() - start_cpu)
        return _with(base, process_factors(("gm", sigma, tau), dt_k)), x


def _with(base: gtsam.NonlinearFactorGraph, factors: list) -> gtsam.NonlinearFactorGraph:
    """A copy of `base` with `factors` added."""
    g = gtsam.NonlinearFactorGraph(base)
    for f in factors:
        g.add(f)
    return g
