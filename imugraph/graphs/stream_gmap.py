"""The gyro map E estimated by the stream's end-of-stream graph (StreamOptions.gyro_map_end; issue 3, BROAD 01/04).

Model (as the batch, imugraph.calibration.gyro_map): ω = (I + E)·b_gyr − b, e = vec E row-major. The stream
preintegrates each keyframe interval k once, at the start calibration's Ê₀ and bias b̂, into ONE super-sample
ImuFactor (stream.py `_close`: ω̄_k = Log ΔR_k / Δt_k + b̂). A change δe of E moves ΔR_k to first order as

    ΔR_k(δe) ≈ ΔR_k Exp(J_k δe),   J_k = ΔR_kᵀ Σ_j R_{j+1} J_r(θ_j) Δt_j (I₃ ⊗ ω_jᵀ)                    (1)

(R_{j+1} = kRb_j Exp(θ_j), θ_j = (ω_j − b̂)Δt_j: gyro_map.py's formula, Forster et al. 2017 eq. 44). The super-sample
factor corrects its rotation for a bias change δb as Exp(θ̄_k − Δt_k δb), i.e. ΔR_k Exp(−J_r(θ̄_k) Δt_k δb) to first
order (θ̄_k = Log ΔR_k), so a change of E acts on interval k exactly like the bias change

    β_k − b_s(k) = C_k δe,   C_k = (−J_r(θ̄_k) Δt_k)⁻¹ J_k                                               (2)

The end graph then gives every CLEAN interval's ImuFactor its own bias key β_k tied linearly to the segment bias and
e (gyro_map_block's block, 6-d ConstantBias keys: the accelerometer half tied to b_s), with the batch's priors
(Ê₀ + e_base + e)/σ_e and S(Ê₀ + e_base + e)/σ_rot; e is estimated jointly with the orientations, no alternation.

Per interval the stream keeps J_k (3×9 floats, the per-keyframe row; `interval`, only with the option); an interval
informs E when every sample has | |a| − g | < Options.gyro_map_acc_tol (gyro_map.clean_intervals). The coverage gate
(clean turns Σ|ω|Δt/2π ≥ Options.gyro_map_min_turns, else E stays Ê₀ and the end graph is the plain one) is counted
as the batch counts it, on the batch's 0.2 s keyframe intervals (running sums, `_gate_rows`): BROAD 04/24/32/06/07
20.13/29.33/14.79/10.85/9.01 turns here, 20.13/29.29/14.9/10.9/9.6 in calibration.ml.

Settling (mirrors calibration.ml's rounds): round r solves the graph with every interval's super-sample rotation moved
to Ê₀ + e_base by (1) (ΔR_k Exp(J_k e_base): the first-order re-preintegration, on ALL intervals, as the batch
preintegrates every sample at Ê) and the clean ones carrying the free e by (2); e_base += ê. A step larger than
Options.gyro_map_max_contraction × the one before, or no settling to Options.gyro_map_tol within MAX_ROUNDS, is the
batch's fallback: the plain end graph (E = Ê₀). Else the graph returned for the final LM is the last round's.
In the stream the rounds change only the first-order re-preintegration of the intervals (the batch's also re-estimate
the noise levels, θ and the velocity process), so this rule rarely bites: BROAD 24, where the batch's E did not settle
(contraction 0.51), settles here at 0.15. gyro_map_end="split" adds `split_check`: one more solve with one e per half
of the clean intervals, E kept only where the halves agree (docs/stream.md "Session 18, helper E").
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from imugraph.factors.gyro import exp_and_right_jacobian
from imugraph.graphs.gyro_map_block import _ANTI, E_KEY, beta_key, without_map_keys

MAX_ROUNDS = 4          # the batch settles in 3–4 rounds on 01/02/04 (step ratio 0.12–0.39)
SIGMA_C = 1e-6          # the linear tie's std (gyro_map_block.GyroMapBlock.sigma_c)
SPLIT_KEYS = (gtsam.symbol("e", 1), gtsam.symbol("e", 2))     # split_check: e of each half's clean intervals


def map_jacobian_interval(t: np.ndarray, w: np.ndarray, kRb: np.ndarray, delta_R: np.ndarray,
                          b_hat: np.ndarray) -> np.ndarray:
    """J_k (3, 9) of eq. (1) for one interval: samples at t[:n] with the gyro as preintegrated w (n, 3), rad/s,
    kRb (n, 3, 3) = R_0 … R_{n−1}, delta_R = R_n, bias b̂."""
    dt = t[1:] - t[:-1]
    _, jr = exp_and_right_jacobian((w - b_hat) * dt[:, None])
    R_next = np.concatenate([kRb[1:], delta_R[None]])                     # R_{j+1} = R_j Exp(θ_j)
    P = R_next @ jr * dt[:, None, None]
    S = np.einsum("jab,jc->abc", P, w).reshape(3, 9)                      # Σ_j P_j (I₃ ⊗ ω_jᵀ)
    return delta_R.T @ S


def equivalent_bias(J: np.ndarray, delta_R: np.ndarray, dt_k: float) -> np.ndarray:
    """C_k (3, 9) of eq. (2): the bias change of the super-sample factor that moves its rotation as δe does."""
    phi = gtsam.Rot3.Logmap(gtsam.Rot3(delta_R))
    _, jr = exp_and_right_jacobian(phi[None])
    return np.linalg.solve(-jr[0] * dt_k, J)


class EndGyroMap:
    """Per-interval J_k and E's gates while streaming; the end graph's E (`extend`, one of StreamSmoother's
    `_end_extensions`). `info`: {"clean_turns", "clean_intervals", "intervals", "estimated", "reason", "E",
    "steps", "contraction", "rounds"} after `finish` (E: the total Ê₀ + ê, row-major 3×3)."""

    def __init__(self, owner):
        from imugraph.calibration.options import Options

        o = Options()
        self.owner = owner
        self.acc_tol, self.min_turns = o.gyro_map_acc_tol, o.gyro_map_min_turns
        self.sigma_e, self.tol, self.max_contraction = o.gyro_map_sigma, o.gyro_map_tol, o.gyro_map_max_contraction
        self.sigma_rot = 1e-3                            # gyro_map_block.GyroMapBlock.sigma_rot
        self.e0 = np.asarray(owner.cal.gyro_map, float).ravel()     # Ê₀, already applied to the pushed gyro
        self.J: dict = {}                                # k → J_k (3, 9), every interval but a bridged gap
        self.clean: set = set()
        self.turns, self.n = 0.0, 0
        # the coverage gate on the BATCH's keyframe intervals (Options.keyframe_hz, 5 Hz; the stream's are 10 Hz):
        # a 0.2 s interval is clean less often than a 0.1 s one (BROAD 06: 10.9 clean turns the batch's way, 21.2
        # on the stream's intervals). Running sums: the open batch interval's index, worst deviation, turns.
        self.stride_b = max(1, int(round(owner.rate / o.keyframe_hz)))
        self.dirty: set = set()                          # batch intervals that are not clean
        self.span: dict = {}                             # clean stream interval → (first, last) batch interval
        self.i_sample, self.b_open, self.b_worst, self.b_turns = 0, 0, 0.0, 0.0
        self.info: dict = {"estimated": False}
        self.split = owner.opt.gyro_map_end == "split"
        self.batch_clean = owner.opt.gyro_map_end == "batch_clean"

    def interval(self, k: int, t: np.ndarray, w: np.ndarray, acc: np.ndarray, kRb: np.ndarray, delta_R: np.ndarray,
                 bridged: bool) -> None:
        """Interval k closed (t (n+1,), w, acc (n, 3) as pushed; kRb, delta_R of its preintegration)."""
        self.n += 1
        dev = np.abs(np.linalg.norm(acc, axis=1) - self.owner._g)
        dev = np.where(np.isfinite(dev), dev, np.inf)
        turn = np.linalg.norm(w, axis=1) * (t[1:] - t[:-1]) / (2 * np.pi)     # gyro_map.clean_turns, per sample
        m0 = self.i_sample // self.stride_b
        self._gate_rows(dev, turn)
        if bridged:             # stream_bridge's preintegration is not eq. (1)'s: no J_k, never informs E
            return
        self.J[k] = map_jacobian_interval(t, w, kRb, delta_R, self.owner._b_hat)
        if self.acc_tol is None or bool(np.all(dev < self.acc_tol)):      # gyro_map.clean_intervals (this interval)
            self.clean.add(k)
            self.span[k] = (m0, (self.i_sample - 1) // self.stride_b)     # its batch intervals (clean_as_batch)

    def _gate_rows(self, dev: np.ndarray, turn: np.ndarray) -> None:
        """Samples in arrival order into the batch-interval running sums (coverage gate)."""
        m = (self.i_sample + np.arange(len(dev))) // self.stride_b
        self.i_sample += len(dev)
        for mm in np.unique(m):
            if mm != self.b_open:
                self._gate_close()
                self.b_open = int(mm)
            sel = m == mm
            self.b_worst = max(self.b_worst, float(dev[sel].max()))
            self.b_turns += float(turn[sel].sum())

    def _gate_close(self) -> None:
        if self.acc_tol is None or self.b_worst < self.acc_tol:
            self.turns += self.b_turns
        else:
            self.dirty.add(self.b_open)
        self.b_worst, self.b_turns = 0.0, 0.0

    def clean_as_batch(self) -> set:
        """gyro_map_end="batch_clean": the clean stream intervals whose batch intervals are all clean (E informed by
        the batch's clean rows: a 0.1 s interval next to fast motion is clean here, its 0.2 s batch interval not).
        Measured worse (BROAD 01: the more intervals E is applied to but not fitted on, the larger the second
        round's step: contraction 0.10 → 0.53, E dropped); not the default of the option."""
        return {k for k in self.clean if not any(m in self.dirty for m in range(self.span[k][0], self.span[k][1] + 1))}

    # ------------------------------------------------------------------ end of stream
    def extend(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        """(graph, values) → the end graph with E (gate and settling passed), else unchanged; info["cpu_s"]: this
        thread's CPU time of the rounds (the final LM on the returned graph is not counted)."""
        start = time.thread_time()
        try:
            return self._extend(graph, values)
        finally:
            self.info["cpu_s"] = time.thread_time() - start

    def _extend(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        self._gate_close()                     # the last batch interval
        if self.batch_clean:
            self.clean = self.clean_as_batch()
        info = self.info = {"clean_turns": self.turns, "clean_intervals": len(self.clean), "intervals": self.n,
                            "estimated": False, "E": self.e0.reshape(3, 3).tolist(), "steps": []}
        if self.turns < self.min_turns or not self.clean:
            info["reason"] = f"coverage: {self.turns:.1f} clean turns < {self.min_turns}"
            return graph, values
        e_base, cur, steps = np.zeros(9), values, []
        for _ in range(MAX_ROUNDS):
            g2, v2 = self.build(graph, cur, e_base)
            try:
                sol = self.owner._final_lm(g2, v2)
            except RuntimeError as err:                    # an indeterminate system: the plain graph
                info["reason"] = f"solve failed: {err}"
                return graph, values
            d_e = np.asarray(sol.atVector(E_KEY), float)
            e_base = e_base + d_e
            steps.append(float(np.max(np.abs(d_e))))
            cur = without_map_keys(sol)
            info["steps"] = steps
            if len(steps) > 1 and steps[-1] > self.max_contraction * steps[-2]:
                info["contraction"] = steps[-1] / steps[-2] if steps[-2] > 0 else None
                info["reason"] = f"E did not settle (contraction {info['contraction']:.3g})"
                info["E_unsettled"] = (self.e0 + e_base).reshape(3, 3).tolist()
                return graph, values
            if len(steps) > 1 and steps[-1] < self.tol:
                break
        else:
            info["reason"] = f"E did not settle to {self.tol} in {MAX_ROUNDS} rounds"
            info["E_unsettled"] = (self.e0 + e_base).reshape(3, 3).tolist()
            return graph, values
        info.update(rounds=len(steps), contraction=steps[-1] / steps[-2] if steps[-2] > 0 else 0.0)
        if self.split and not self.split_check(graph, cur, e_base):
            info["E_unsettled"] = (self.e0 + e_base).reshape(3, 3).tolist()
            return graph, values
        info.update(estimated=True, E=(self.e0 + e_base).reshape(3, 3).tolist())
        self.e_base = e_base
        return self.build(graph, cur, e_base)

    def total(self, values: gtsam.Values) -> np.ndarray:
        """Ê (3, 3) of a solution of the extended graph: Ê₀ + e_base + e."""
        return (self.e0 + self.e_base + np.asarray(values.atVector(E_KEY), float)).reshape(3, 3)

    def split_check(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, e_base: np.ndarray) -> bool:
        """gyro_map_end="split": the settled graph solved once more with one e for the clean intervals of each half
        of the recording (by count): Ê is kept only when the halves agree, max|ê_A − ê_B| ≤ max_contraction ×
        max|Ê₀ + e_base| over E's symmetric part (the antisymmetric one is the prior's, gyro_map_block). A sensor's
        scale/misalignment is the same in both halves; an E that follows the motion of each half is not one."""
        clean = sorted(self.clean)
        half = {k: (SPLIT_KEYS[0] if i < len(clean) // 2 else SPLIT_KEYS[1]) for i, k in enumerate(clean)}
        g2, v2 = self.build(graph, values, e_base, half)
        try:
            sol = self.owner._final_lm(g2, v2)
        except RuntimeError as err:
            self.info["reason"] = f"split solve failed: {err}"
            return False
        e_a, e_b = (np.asarray(sol.atVector(key), float) for key in SPLIT_KEYS)
        tot = self.e0 + e_base
        sym = lambda e: 0.5 * (e.reshape(3, 3) + e.reshape(3, 3).T)      # noqa: E731
        ratio = float(np.max(np.abs(sym(e_a - e_b))) / max(np.max(np.abs(sym(tot))), 1e-12))
        self.info.update(E_first_half=(tot + e_a).reshape(3, 3).tolist(), E_second_half=(tot + e_b).reshape(3, 3).tolist(),
                         split_ratio=ratio)
        if ratio > self.max_contraction:
            self.info["reason"] = f"halves disagree (ratio {ratio:.3g})"
            return False
        return True

    def build(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, e_base: np.ndarray,
              groups: dict | None = None):
        """The end graph with every interval's super-sample rotation at Ê₀ + e_base (eq. 1) and the clean intervals'
        factors on β_k = b_s + C_k e (eq. 2), the ties and E's priors; values with β_k = b_s and e = 0. groups: clean
        interval → the key of its e (split_check), else E_KEY for all."""
        out, vals = gtsam.NonlinearFactorGraph(), gtsam.Values(values)
        lin = gtsam.Values()
        unit6 = gtsam.noiseModel.Unit.Create(6)
        eye6 = np.eye(6) / SIGMA_C
        ties: dict = {}
        for i in range(graph.size()):
            if not graph.exists(i):
                continue
            f = graph.at(i)
            if not isinstance(f, (gtsam.ImuFactor, gtsam.ImuFactorWithGravityVector)):
                out.add(f)
                continue
            kk = f.keys()
            k = int(gtsam.Symbol(kk[0]).index())
            J = self.J.get(k)
            if J is None:
                out.add(f)
                continue
            pim0 = f.preintegratedMeasurements()
            dt_k = float(pim0.deltaTij())
            b_hat = pim0.biasHat()
            dR = pim0.deltaRij().matrix()
            if np.any(e_base):       # ΔR_k Exp(J_k e_base): the super sample integrated again (stream.py _close)
                dR = dR @ gtsam.Rot3.Expmap(J @ e_base).matrix()
                pim = gtsam.PreintegratedImuMeasurements(self.owner._pim_params, b_hat)
                omega = gtsam.Rot3.Logmap(gtsam.Rot3(dR)) / dt_k + b_hat.gyroscope()
                pim.integrateMeasurement(np.asarray(pim0.deltaVij(), float) / dt_k, omega, dt_k)
            else:
                pim = pim0
            bias = kk[4]
            if k in self.clean:
                bias = beta_key(k)
                ties[k] = (kk[4], equivalent_bias(J, dR, dt_k), E_KEY if groups is None else groups[k])
            ends = (kk[0], kk[1], kk[2], kk[3], bias)
            g = gtsam.ImuFactorWithGravityVector(*ends, kk[5], pim) if len(kk) == 6 else gtsam.ImuFactor(*ends, pim)
            out.add(g.cloneWithNewNoiseModel(f.noiseModel()))
        if not ties:
            return out, values
        gfg = gtsam.GaussianFactorGraph()
        zero_b = gtsam.imuBias.ConstantBias()
        for k, (b_key, C, e_key) in ties.items():     # (β_k − b_s − [0; C_k e]) / σ_c = 0 (ConstantBias: acc, gyro)
            A_e = np.zeros((6, 9))
            A_e[3:] = -C / SIGMA_C
            gfg.push_back(gtsam.JacobianFactor(beta_key(k), eye6, b_key, -eye6, e_key, A_e, np.zeros(6), unit6))
            for key in (beta_key(k), b_key):
                if not lin.exists(key):
                    lin.insert(key, zero_b)
            if not vals.exists(beta_key(k)):
                vals.insert(beta_key(k), values.atConstantBias(b_key))
        tot = self.e0 + e_base                 # (Ê₀ + e_base + e)/σ_e, S(…)/σ_rot (gyro_map_block)
        A = np.r_[np.eye(9) / self.sigma_e, _ANTI / self.sigma_rot]
        for e_key in sorted({tie[2] for tie in ties.values()}):
            gfg.push_back(gtsam.JacobianFactor(e_key, A, -np.r_[tot / self.sigma_e, _ANTI @ tot / self.sigma_rot],
                                               gtsam.noiseModel.Unit.Create(12)))
            lin.insert(e_key, np.zeros(9))
            vals.insert(e_key, np.zeros(9))
        lcf = gtsam.LinearContainerFactor.ConvertLinearGraph(gfg, lin)
        for i in range(lcf.size()):
            out.add(lcf.at(i))
        return out, vals

