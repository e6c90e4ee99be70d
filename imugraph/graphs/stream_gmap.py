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

gyro_map_end="exact" (session 19, helper Z): the rounds the batch's way. The stream keeps every interval's gyro rows
as pushed (at Ê₀) and re-timed accelerometer rows (`interval`, 6 floats per sample), and each round re-preintegrates
ALL samples with the batch's code (factors.gyro.preintegrate, calibration.gyro_map.map_jacobian,
factors.velocity.velocity_increments) at the current Ê = Ê₀ + e_base and the current bias estimate b̂_s(k) of each
interval's segment (calibration.ml's solve_round: ω_j = (I + Ê)(I + Ê₀)⁻¹ w_j, eq. 3): ΔR_k, J_k, C_k (eq. 2, at
the new ΔR_k and b̂), Δv_k (the intra-interval rotations R_j under the accelerometer rows) all new; the super-sample
factor is rebuilt at that bias (biasHat = b̂_s(k)); the noise models and the magnetometer factors (their averaged
rows under R_j) are kept. "exact_batch_clean": the same with E informed by the batch's clean 0.2 s intervals
(`clean_as_batch`). Measured (docs/stream.md "Session 19, helper Z"): the exact rounds give the first-order ones'
steps and Ê (BROAD 01/02/04/24 within 0.01 %, 24 still settles at 0.15): the difference from the batch is its MODEL,
not the re-preintegration — the batch's rounds with θ's D held settle on 24 (0.22), and with θ held at 10 Hz
keyframes come within 0.06 / 0.10 % per entry of the stream's Ê on 04 / 24 (the default batch: 0.39 % on 04;
benchmarks/z19_batch_theta_hold.py). "theta" (diagnostic): θ free in the E rounds (`_free_theta`), as the batch's
(BROAD 24 then creeps, 0.54, and falls back like the batch); "theta_gate": those rounds only as the settling gate
(E then from the θ-held rounds, as gyro_map_end=True). "theta_e" (session 19, helper Z2): the same gate, but E is
the θ-FREE rounds' Ê, held fixed: the final graph is the θ-held end graph with every interval's rotation moved to it by
(1) and no e variable (build(free_e=False)) — separates the θ-free rounds' E from θ staying free in the final graph.
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from imugraph.calibration.gyro_map import corrected_rate, map_jacobian
from imugraph.factors.gyro import exp_and_right_jacobian, preintegrate
from imugraph.factors.velocity import velocity_increments
from imugraph.graphs.cpp_velocity import super_sample_pim
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
        mode = owner.opt.gyro_map_end
        self.split = mode == "split"
        self.batch_clean = mode in ("batch_clean", "exact_batch_clean")
        self.exact = mode in ("exact", "exact_batch_clean")
        self.theta = {"theta": "free", "theta_gate": "gate", "theta_e": "e"}.get(mode) if isinstance(mode, str) else None
        self.rows: list = []                             # "exact": per interval (w (n, 3) as pushed, acc (n, 3) used)

    def interval(self, k: int, t: np.ndarray, w: np.ndarray, acc: np.ndarray, kRb: np.ndarray, delta_R: np.ndarray,
                 bridged: bool, acc_used: np.ndarray) -> None:
        """Interval k closed (t (n+1,), w, acc (n, 3) as pushed; kRb, delta_R of its preintegration; acc_used: the
        accelerometer rows its Δv integrated, re-timed by δ — kept for "exact")."""
        self.n += 1
        if self.exact:          # the samples of the end's exact re-preintegration (every interval: the layout)
            self.rows.append((np.array(w, float), np.array(acc_used, float)))
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
            if not self.theta:
                return self._extend(graph, values)
            freed = self._free_theta(graph, values)       # "theta": θ a variable of the E rounds (stream_windows_end)
            if freed is None:
                self.info = {"estimated": False, "E": self.e0.reshape(3, 3).tolist(), "steps": [],
                             "reason": "theta: the end magnetometer factors were not found"}
                return graph, values
            g_free, v_free, ext, was_free = freed
            out = self._extend(g_free, v_free, keep=self.theta == "free")     # the θ-free graph kept by "theta" only
            self.info["theta_free"] = True
            if not self.info.get("estimated") or self.theta != "free":     # θ as before
                ext._theta_free = was_free
            if not self.info.get("estimated"):            # the fallback: the plain end graph
                return graph, values
            if self.theta == "gate":          # settled with θ free: E from the θ-held rounds (as gyro_map_end=True)
                check = {key: self.info.get(key) for key in ("steps", "contraction", "E")}
                out = self._extend(graph, values)
                self.info["theta_check"] = check
            if self.theta == "e":             # settled with θ free: that Ê fixed in the θ-held end graph (eq. 1)
                self.info["theta_e"] = True
                return self.build(graph, values, self.e_base, free_e=False)
            return out
        finally:
            self.info["cpu_s"] = time.thread_time() - start

    def _free_theta(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        """gyro_map_end="theta" (diagnostic, session 19): the end graph with θ = (D, o, dip) FREE as in the batch's ML
        rounds — stream_windows_end's θ-free magnetometer factors and weak prior Λ_w about θ_n (windows_end's
        machinery, reused) — so that E is estimated jointly with D, as calibration.ml does. (graph, values, ext, θ was
        free already) or None (no EndWindows extension, or its factors not found)."""
        from imugraph.graphs.stream_windows_end import end_windows

        ext = end_windows(self.owner)
        if ext is None:
            return None
        if ext._theta_free:                  # a modelled window freed θ already
            return graph, values, ext, True
        base = ext._base(graph)
        if base is None:
            return None
        values = gtsam.Values(values)
        ext._theta_free = True
        return ext._graph(ext._free_base(graph, base, values), values), values, ext, False

    def _extend(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keep: bool = True):
        self._gate_close()                     # the last batch interval
        if self.batch_clean:
            self.clean = self.clean_as_batch()
        info = self.info = {"clean_turns": self.turns, "clean_intervals": len(self.clean), "intervals": self.n,
                            "estimated": False, "E": self.e0.reshape(3, 3).tolist(), "steps": []}
        if self.exact:          # memory of the kept rows (w, acc: 6 floats per sample)
            info.update(exact=True, bytes_per_keyframe=sum(w.nbytes + a.nbytes for w, a in self.rows) / max(self.n, 1))
        if self.turns < self.min_turns or not self.clean:
            info["reason"] = f"coverage: {self.turns:.1f} clean turns < {self.min_turns}"
            return graph, values
        e_base, cur, steps = np.zeros(9), values, []
        for _ in range(MAX_ROUNDS):
            g2, v2 = self.build(graph, cur, e_base, exact=self.exact)
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
        return self.build(graph, cur, e_base, exact=self.exact) if keep else (graph, values)

    def total(self, values: gtsam.Values) -> np.ndarray:
        """Ê (3, 3) of a solution of the extended graph: Ê₀ + e_base + e."""
        e = np.asarray(values.atVector(E_KEY), float) if values.exists(E_KEY) else 0.0     # "theta_e": e fixed
        return (self.e0 + self.e_base + e).reshape(3, 3)

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

    def repreintegrate(self, e_base: np.ndarray, b_k: np.ndarray) -> tuple:
        """"exact": every interval's samples integrated again at Ê = Ê₀ + e_base and bias b_k (K−1, 3) per interval
        with the batch's code, as calibration.ml's solve_round: (ΔR (K−1, 3, 3), J (K−1, 3, 9), Δv (K−1, 3)).
        ω_j = (I + Ê) b_gyr,j with b_gyr,j = (I + Ê₀)⁻¹ w_j the recorded rate (eq. 3)."""
        o = self.owner
        n_int = len(self.rows)
        lengths = np.array([len(r[0]) for r in self.rows] + [1])       # + the last keyframe's own (dummy) sample
        w = np.concatenate([r[0] for r in self.rows] + [np.zeros((1, 3))])
        acc = np.concatenate([r[1] for r in self.rows] + [np.zeros((1, 3))])
        raw = w if o._IE_inv is None else w @ o._IE_inv
        g_c = corrected_rate(raw, (self.e0 + e_base).reshape(3, 3))
        t = np.concatenate(o._hist_t[:n_int] + [np.array([o._kf_t[n_int]])])
        dt = np.r_[np.diff(t), 0.0]
        kf = np.r_[0, np.cumsum(lengths[:-1])]
        skf = np.repeat(np.arange(n_int + 1), lengths)
        b_rows = np.r_[b_k, b_k[-1:]][skf]
        pre = preintegrate(g_c, dt, kf, skf, b_rows, o._sig_g, o.opt.gyro_rate_error, keep_steps=True, gap_walk=None)
        J = map_jacobian(g_c, dt, pre, b_rows)
        dv, _ = velocity_increments(pre.kRb, skf, acc, dt, n_int + 1, o._sig_acc, o.opt.acc_rate_error, gap_walk=None)
        return pre.delta_R, J, dv

    def _exact_inputs(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, e_base: np.ndarray) -> tuple:
        """repreintegrate at the bias estimate of each interval's segment in `values` (the ImuFactors' bias keys)."""
        b_k = np.tile(np.asarray(self.owner._b_hat, float), (len(self.rows), 1))
        for i in range(graph.size()):
            f = graph.at(i) if graph.exists(i) else None
            if isinstance(f, (gtsam.ImuFactor, gtsam.ImuFactorWithGravityVector)):
                k = int(gtsam.Symbol(f.keys()[0]).index())
                if k < len(b_k):
                    b_k[k] = values.atConstantBias(f.keys()[4]).gyroscope()
        return (*self.repreintegrate(e_base, b_k), b_k)

    def build(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, e_base: np.ndarray,
              groups: dict | None = None, exact: bool = False, free_e: bool = True):
        """The end graph with every interval's super-sample rotation at Ê₀ + e_base (eq. 1) and the clean intervals'
        factors on β_k = b_s + C_k e (eq. 2), the ties and E's priors; values with β_k = b_s and e = 0. groups: clean
        interval → the key of its e (split_check), else E_KEY for all. exact: each interval's factor from the samples
        re-preintegrated at Ê₀ + e_base and the current bias (`repreintegrate`), J_k and C_k there. free_e=False
        ("theta_e"): E fixed at Ê₀ + e_base, no β_k, ties or e (every factor on its segment bias)."""
        ex = self._exact_inputs(graph, values, e_base) if exact else None
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
            if ex is not None:       # the samples at Ê₀ + e_base and b̂_s(k) (eq. 3): the super sample of stream.py _close
                dR, J = ex[0][k], ex[1][k]
                omega = gtsam.Rot3.Logmap(gtsam.Rot3(dR)) / dt_k + ex[3][k]
                pim = super_sample_pim(self.owner._pim_params, omega, ex[2][k] / dt_k, dt_k, ex[3][k])
            elif np.any(e_base):     # ΔR_k Exp(J_k e_base): the super sample integrated again (stream.py _close)
                dR = dR @ gtsam.Rot3.Expmap(J @ e_base).matrix()
                pim = gtsam.PreintegratedImuMeasurements(self.owner._pim_params, b_hat)
                omega = gtsam.Rot3.Logmap(gtsam.Rot3(dR)) / dt_k + b_hat.gyroscope()
                pim.integrateMeasurement(np.asarray(pim0.deltaVij(), float) / dt_k, omega, dt_k)
            else:
                pim = pim0
            bias = kk[4]
            if free_e and k in self.clean:
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

