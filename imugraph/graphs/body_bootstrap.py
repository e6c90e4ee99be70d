"""How long the batch bootstrap of the incremental body estimator must be: until the body has moved enough.

Without magnetometers a sensor's heading relative to its neighbours — hence its sensor-to-segment rotation
bRs, which the incremental solvers take from the bootstrap and then hold — is observable only once the joints
it shares have accelerated horizontally and the segments have turned (Kok et al. 2014; tests/test_body_graph:
a static session keeps a 25° start error). The bootstrap therefore ends at the first sample where EVERY
sensor s has, since the end of the N-pose i₀,

    Σ_{i>i₀} max(0, |ω_i − b̂_s| − 0.05 rad/s) dt_i ≥ min_turn_rad              (turned)
    Σ_{k: kf_k>i₀} max(0, |nR̂s_k a_k − ā_s| − 0.1 m/s²) Δt_k ≥ min_dv          (accelerated)          (A1)

with b̂_s the N-pose mean gyro reading, nR̂s_k the initial orientation of the graph at keyframe k (the gyro
integrated from the N-pose tilt, imugraph.graphs.body_init), ā_s = N-pose mean of nR̂s a (≈ g ẑ) and Δt_k
the keyframe interval: the free acceleration, whose HORIZONTAL part is what fixes relative headings (|a|
alone barely changes with it: |g ẑ + a_h| − g ≈ |a_h|²/2g). The dead bands keep noise and standing sway
(≲ 0.04 rad/s on the gaittoolbox walk) from counting. It lasts at least `min_after_npose_s`
beyond the N-pose and at most `max_s` (then info["bootstrap"]["motion_reached"] is False).

Measured (gaittoolbox S02 walk, 7 MTw at 100 Hz, standing to ≈ 11 s, fixed lag 2 s, offset handling vs Vicon,
batch 5.03°): a bootstrap to 12 s (1 s of walking) 5.72°, 13 s 5.09°, 15 s 4.98°; the defaults 1 rad and
2 m/s end it at ≈ 13 s.
"""

from __future__ import annotations

import numpy as np

from imugraph.factors import body as bf

MIN_TURN_RAD = 1.0
MIN_DV = 2.0          # m/s
GYR_DEADBAND = 0.05   # rad/s
ACC_DEADBAND = 0.1    # m/s²


def motion_bootstrap_s(session, pb, min_turn_rad: float = MIN_TURN_RAD, min_dv: float = MIN_DV,
                       min_after_npose_s: float = 1.0, max_s: float = 30.0) -> tuple[float, dict]:
    """(bootstrap length in s from the first sample, details) by criterion (A1) (module docstring).

    Args:
        session: the BodySession; pb: its `imugraph.graphs.body.BodyProblem` (names, set-ups, N-pose,
            keyframes, initial values).
    """
    t = np.asarray(session.t, float)
    i0 = int(pb.npose_idx[-1])
    kf = np.asarray(pb.kf)
    dt_kf = np.diff(t[kf], append=t[kf[-1]])
    ends = {}
    for s, name in enumerate(pb.names):
        sen = session.sensors[name]
        w = np.maximum(np.linalg.norm(sen.gyr - pb.setups[name].gyro_bias0, axis=1) - GYR_DEADBAND, 0.0) * sen.dt
        w[: i0 + 1] = 0.0
        nR = np.stack([pb.init.atPose3(bf.pose_key(s, k)).rotation().matrix() for k in range(kf.size)])
        n_a = np.einsum("kij,kj->ki", nR, sen.acc[kf])
        a_ref = n_a[kf <= i0].mean(axis=0) if np.any(kf <= i0) else np.array([0.0, 0.0, 9.81])
        a = np.maximum(np.linalg.norm(n_a - a_ref, axis=1) - ACC_DEADBAND, 0.0) * dt_kf
        a[kf <= i0] = 0.0
        dv = np.zeros(t.size)
        dv[kf] = a
        ok = (np.cumsum(w) >= min_turn_rad) & (np.cumsum(dv) >= min_dv)                                # (A1)
        ends[name] = int(np.argmax(ok)) if ok.any() else None
    reached = all(e is not None for e in ends.values())
    t_motion = max(t[e] for e in ends.values()) - t[0] if reached else np.inf
    length = float(min(max(t_motion, t[i0] - t[0] + min_after_npose_s), max_s))
    last = max((n for n in ends if ends[n] is not None), key=lambda n: ends[n], default=None)
    return length, {"auto": True, "motion_reached": bool(reached and t_motion <= max_s), "bootstrap_s": length,
                    "last_sensor": last if reached else [n for n, e in ends.items() if e is None],
                    "min_turn_rad": min_turn_rad, "min_dv": min_dv}
