"""gyro_bias_drift as an extension of the body GRAPH (docs/diagnose_body.md §3): the exact refit of a drift.

Why not the first-order (BE1) extension: the base body model has its own gyro-bias random walk (bias per 1 s
segment m, b_m − b_{m−1} ~ N(0, σ_rw² Δt_m), σ_rw = BodyOptions.bias_rw), so an injected drift β(t) goes partly
into the fitted bias path and partly into the orientations, which the joints then bend; measured (Xsens walk,
LeftLowerLeg, docs §3): the bias path took 74 % of a 0.5 °/s linear drift and 29–51 % of a 2 °/s wander, the
rest moved the sensor's joint/pos residuals (1.3–2 × their clean RMS at 2 °/s), while its gyr residual (the
rotation error the graph leaves, ≈ 1e-5 rad/s) stayed at the solver's residue. With the trajectory fixed, a
gyro change only changes that gyr residual (and acc/pos through ΔR̃): the (BE1) columns of a drift are blind to
where the drift's evidence is (its screened G was −0.024 = the BIC cost on every sensor, all channels 0.000).

Extension (exact, all-C++ factors): the sensor's bias random walk gets a deterministic drift,

    b_m − b_{m−1} − (β̄_m − β̄_{m−1}) ~ N(0, σ_rw² Δt_m),  β(t) = Σ_{p=1..3} c_p P_p(τ(t)) (3 × 3 coefficients c,
    a Vector key D(s); β̄_m: the mean of β over segment m's samples; acc rows unchanged)                (BD1)

(a JacobianFactor in a LinearContainerFactor: the bias and c live in vector spaces, so the factor is exactly
linear), the rest of the graph unchanged; solved warm from the base solution (fit.refit_body_warm's problem).
The bias variables b_m remain the full bias; the drift no longer pays the random-walk cost, so it leaves the
orientations and joints. Candidates: the sensors whose base bias path shows the drift most, (BD2) below.

Pre-screen (BD2), from the base fit alone: the random-walk cost the extension would remove to first order,
ΔC_s = ½ Σ_m ‖z_m‖² − min_c ½ Σ_m ‖z_m − D_m c‖², z_m = (b̂_m − b̂_{m−1})/σ_m (gyro rows), the LS of the
fitted increments on the drift's (D_m whitened likewise). It RANKS the sensors; only the best N_GRAPH are
refitted, and the held-out test (run.py (BV)) decides. Measured (Xsens walk, drift on LeftLowerLeg): ΔC 11.8
(2 °/s wander), 2.4 (0.8 °/s linear), 2.2 (0.8 °/s wander) on the drifting sensor against 0.0–0.8 on every
other sensor and on the clean walk. A first rule refitted only when ΔC > k/2 = 4.5 (9 coefficients fitted to
increments at the model's own level, AIC): it missed both 0.8 °/s drifts, which the refit then found or
nearly found (G +0.48, shrink 0.05, fitted 0.82 °/s peak-to-peak; G +1.34, shrink −0.05).
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from imugraph.diagnose.effects.gyro_bias_drift import legendre_basis

N_GRAPH = 1            # graph refits per diagnosis: the best sensor by ΔC (BD2); the held-out test decides
MIN_PRESCREEN = 0.0    # ΔC must be positive (a bias path with no drift-shaped increments is not refitted)
MAX_ITERATIONS = 5     # LM iterations of the warm graph refit (measured, Xsens walk 2 °/s drift: cost 40.3 →
                       # 15.4 after 2, 15.1 after 4, 14.8 after 8, 13.4 after 19 (converged); clean 12.2)


def drift_key(s: int) -> int:
    """D(s): the 9 drift coefficients of sensor s (Vector)."""
    return gtsam.symbol("d", s)


def segment_basis(pb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(first keyframe of each bias segment (M,), Δt between segment starts (M−1,), β̄ basis (M, 3): the mean
    of P_1..P_3 over each segment's samples)."""
    t = np.asarray(pb.session.t, float)
    B = legendre_basis(t, float(t[0]), float(t[-1]))
    seg = np.asarray(pb.bias_seg, int)
    M = int(seg.max()) + 1
    first = np.array([int(np.flatnonzero(seg == m)[0]) for m in range(M)])
    dt = np.diff(np.asarray(pb.kf_t, float)[first])
    sample_seg = seg[np.clip(np.searchsorted(pb.kf, np.arange(t.size), side="right") - 1, 0, pb.K - 1)]
    Bbar = np.stack([B[sample_seg == m].mean(axis=0) if np.any(sample_seg == m) else B[0] for m in range(M)])
    return first, dt, Bbar


def increment_design(pb, s: int, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened gyro increments z (M−1, 3) of sensor s's fitted bias path, the design D (M−1, 3, 9)/σ of (BD1),
    and the segments' mean basis rows Bbar (M, 3) (`segment_basis`)."""
    first, dt, Bbar = segment_basis(pb)
    b = np.stack([np.asarray(x.atConstantBias(pb.bkey(s, int(k))).gyroscope(), float) for k in first])
    sig = pb.opts.bias_rw * np.sqrt(dt)[:, None]
    z = np.diff(b, axis=0) / sig
    dB = np.diff(Bbar, axis=0)                                                       # (M−1, 3) per basis p
    D = np.einsum("mp,ab->mapb", dB, np.eye(3)).reshape(len(dB), 3, 9) / sig[:, :, None]   # c = (p, axis) flat
    return z, D, Bbar


def prescreen(real, sensor: str) -> dict:
    """(BD2) for one sensor of the base fit: {"gain": ΔC, "n_increments", "ptp_deg_s": the first-order drift's
    peak-to-peak from the bias path alone}."""
    pb, x = real.problem, real.values
    if pb is None or pb.opts.bias_rw is None or pb.bias_seg is None or int(np.max(pb.bias_seg)) < 4:
        return {"gain": 0.0, "n_increments": 0, "ptp_deg_s": 0.0}
    s = pb.names.index(sensor)
    z, D, Bbar = increment_design(pb, s, x)
    A, y = D.reshape(-1, 9), z.reshape(-1)
    c = np.linalg.lstsq(A, y, rcond=None)[0]
    gain = 0.5 * float(y @ y - np.sum((y - A @ c) ** 2))
    beta = Bbar @ c.reshape(3, 3)
    return {"gain": gain, "n_increments": int(z.shape[0]),
            "ptp_deg_s": float(np.rad2deg(np.max(np.ptp(beta, axis=0))))}


def extended_graph(pb, sensor: str, graph=None):
    """The base graph with sensor's bias random walk replaced by (BD1); returns (graph, drift key). graph: a
    copy of the base graph of pb to modify (fit.problem_graph; None: full_graph(pb) is built)."""
    from imugraph.graphs.body import full_graph

    s = pb.names.index(sensor)
    g = full_graph(pb) if graph is None else graph
    first, dt, Bbar = segment_basis(pb)
    dkey = drift_key(s)
    walk = {(pb.bkey(s, int(first[m - 1])), pb.bkey(s, int(first[m]))): m for m in range(1, len(first))}
    for i in range(g.size()):
        f = g.at(i)
        if f is None:
            continue
        keys = tuple(f.keys())
        if len(keys) != 2 or keys not in walk:
            continue
        m = walk[keys]
        sig = np.r_[np.full(3, pb.opts.acc_bias_rw), np.full(3, pb.opts.bias_rw)] * np.sqrt(dt[m - 1])
        Dm = np.zeros((6, 9))
        Dm[3:] = np.kron((Bbar[m] - Bbar[m - 1])[None, :], np.eye(3))               # c = (p, axis) flat
        # (BD1) whitened: r = (b_m − b_{m−1} − D_m c)/σ, linear: A δ − b with b = −r at the zero point
        jf = gtsam.JacobianFactor(keys[0], -np.diag(1 / sig), keys[1], np.diag(1 / sig), dkey, -Dm / sig[:, None],
                                  np.zeros(6), gtsam.noiseModel.Unit.Create(6))
        g.replace(i, gtsam.LinearContainerFactor(jf, _zero_point(keys, dkey)))
    return g, dkey


def _zero_point(keys, dkey) -> gtsam.Values:
    """Linearisation point of a (BD1) factor: zero biases and drift (the factor is linear: exact)."""
    v = gtsam.Values()
    for k in keys:
        v.insert(k, gtsam.imuBias.ConstantBias())
    v.insert(dkey, np.zeros(9))
    return v


def refit_drift(real, sensor: str, max_iterations: int | None = MAX_ITERATIONS):
    """θ* of the base model extended by (BD1) on `sensor`, warm from the base solution: (BodyFit, params)."""
    from dataclasses import replace

    from imugraph.diagnose.body.fit import _extract, problem_graph
    from imugraph.diagnose.body.lm import lm_optimize

    pb = real.problem
    if max_iterations is not None:
        pb = replace(pb, opts=replace(pb.opts, max_iterations=int(max_iterations)))
    t0 = time.perf_counter()
    g, dkey = extended_graph(pb, sensor, problem_graph(real))
    x0 = gtsam.Values(real.values)
    x0.insert(dkey, np.zeros(9))
    x, info = lm_optimize(pb, g, x0, real.info.get("lm"))                  # the base fit's LM damping
    c = np.asarray(x.atVector(dkey), float)
    t = np.asarray(pb.session.t, float)
    beta = legendre_basis(t, float(t[0]), float(t[-1])) @ c.reshape(3, 3)
    theta = _extract(pb.session, pb, x, dict(info, warm_start=True, drift_of=sensor), t0)
    params = {"legendre_coefficients_rad_s": c.reshape(3, 3).tolist(),
              "peak_to_peak_deg_s": float(np.rad2deg(np.max(np.ptp(beta, axis=0))))}
    return theta, params


class GraphDrift:
    """The (BD1) extension as seen by the attribution's scoring (run.score_candidate, stage 2): the refitted θ*
    already holds the drift, so `fit` returns θ*'s residuals of the sensor whatever the fold's training rows
    (the 9 coefficients were fitted on all rows: the weak leak of every stage-2 refit, body/refit.py)."""

    name = "gyro_bias_drift"
    channel = "gyr"
    windowed = False

    def __init__(self, params: dict, relevant_deg_s: float):
        self.params = params
        self.relevant = relevant_deg_s

    def fit(self, theta, sensor, train, sigma):
        from imugraph.diagnose.body.effects.base import BodyCorrection

        res = {c: r.copy() for c, r in theta.sensors[sensor].residuals.items()}
        ptp = float(self.params["peak_to_peak_deg_s"])
        return BodyCorrection(self.name, sensor, dict(self.params, extension="graph (BD1)"), 9, self.channel, res,
                              size={"value": ptp, "threshold": self.relevant, "unit": "°/s"})


def graph_drift_candidates(real, sensors, a, b, sigma, opt, base: dict, score, say=print, only=None) -> list:
    """(BD2) pre-screen on every sensor, then (BD1) refits of the best N_GRAPH (ΔC > MIN_PRESCREEN), each scored
    by `score` (run.score_candidate) against the base fit. Returns the stage-2 results (prescreen attached).
    only: a set of sensors (None: all): a picked sensor outside it is not refitted (its screened result stays;
    BodyDiagnoseOptions.refit_located_only)."""
    from imugraph.diagnose.effects.gyro_bias_drift import RELEVANT_DEG_S

    pre = {n: prescreen(real, n) for n in sensors}
    picked = sorted((n for n in sensors if pre[n]["gain"] > MIN_PRESCREEN), key=lambda n: -pre[n]["gain"])[:N_GRAPH]
    if only is not None:
        for n in picked:
            if n not in only:
                say(f"drift graph refit on {n} skipped (no located gap; ΔC {pre[n]['gain']:.1f})")
        picked = [n for n in picked if n in only]
    out = []
    for n in picked:
        try:
            theta, params = refit_drift(real, n)
        except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:
            say(f"drift graph refit on {n} failed ({type(exc).__name__}: {str(exc)[:200]})")
            continue
        r = score(GraphDrift(params, RELEVANT_DEG_S), real, a, b, sigma, n, opt, theta, base=base[n])
        r["prescreen"] = pre[n]
        r["refit_iterations"] = [int(theta.info.get("iterations", -1))]
        say(f"drift graph refit on {n}: ΔC {pre[n]['gain']:.1f}, G {r['loglik_gain']:+.3f}, shrink {r['shrink']:.2f}, "
            f"ptp {params['peak_to_peak_deg_s']:.2f} °/s")
        out.append(r)
    return out
