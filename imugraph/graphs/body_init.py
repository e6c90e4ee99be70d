"""Initial values of the body estimator: each sensor on its own, then forward kinematics through the joints.

Orientation: at the N-pose the segments are world-aligned with heading ψ₀ (npose_heading_deg), so the
sensor's nominal orientation is nRs = Rz(ψ₀)·bRs_nominal; its tilt is corrected to the N-pose mean
accelerometer direction (the smallest rotation taking nRs·ā/|ā| to +z). With magnetometers, every sensor's
heading is turned so that its horizontal field points where the root sensor's does. Then the gyro (minus the
N-pose mean rate, the bias) is integrated: q_{k+1} = q_k ⊗ Exp((ω_k − b̂) dt_k), all sensors at once
(`integrate_gyro_sensors`: the same floating-point operations as imugraph.geometry.integrate_gyro per sensor,
one numpy step per sample for every sensor instead of one `quat_mul` call per sample and sensor).

Positions: the root sensor at the origin (its translation is left to the solver: it enters the IMU factors
linearly once orientations are close); every other sensor by the joints with the nominal lever arms,
J = p_P + nRs_P l_P,  p_C = J − nRs_C l_C.  Velocities: central differences of those keyframe positions.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.errors import SessionError
from imugraph.factors import body as bf
from imugraph.geometry import expmap, integrate_gyro, quat_to_rotmat, rotmat_to_quat
from imugraph.graphs.body_model import BodyJoint, SensorSetup


def rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector u onto unit vector v (3, 3)."""
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    axis = np.cross(u, v)
    s, c = np.linalg.norm(axis), float(np.dot(u, v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        w = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])   # any axis ⟂ u
        return expmap(np.pi * w / np.linalg.norm(w))
    return expmap(axis / s * np.arctan2(s, c))


def rz(psi: float) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def initial_orientations(session, names: list[str], setups: dict[str, SensorSetup], npose_idx: np.ndarray,
                         psi0: float, use_mag: bool, stop: int | None = None) -> dict[str, np.ndarray]:
    """Per-sample initial nRs (N, 3, 3) for every sensed segment (module docstring); stop: only the samples
    [:stop] (the integration is causal: the same values as the first `stop` of all N)."""
    nRs0 = {}
    for name in names:
        s, st = session.sensors[name], setups[name]
        a = s.acc[npose_idx].mean(axis=0)
        R_nom = rz(psi0) @ st.bRs_nom
        nRs0[name] = rotation_between(R_nom @ a, np.array([0.0, 0.0, 1.0])) @ R_nom
    if use_mag:
        def field_heading(name):
            m = session.sensors[name].mag[npose_idx]
            m = m[np.all(np.isfinite(m), axis=1)]
            if m.shape[0] == 0:
                raise SessionError(session.source, f"sensors[{name}].mag", "no magnetometer sample in the N-pose",
                                   "magnetometer samples (or use_mag=False)")
            n_m = nRs0[name] @ m.mean(axis=0)
            return float(np.arctan2(n_m[1], n_m[0]))
        ref = field_heading(names[0])
        for name in names[1:]:
            nRs0[name] = rz(ref - field_heading(name)) @ nRs0[name]
    q = integrate_gyro_sensors([session.sensors[n].gyr[:stop] - setups[n].gyro_bias0 for n in names],
                               [session.sensors[n].dt[:stop] for n in names], [rotmat_to_quat(nRs0[n]) for n in names])
    return {name: quat_to_rotmat(q[i]) for i, name in enumerate(names)}


def integrate_gyro_sensors(gyr: list, dt: list, q0: list) -> list:
    """Strapdown integration of S sensors on a common sample count N: imugraph.geometry.integrate_gyro of each
    sensor (bit for bit), one broadcast step per sample for all sensors (tests/test_diagnose_body_speed.py)."""
    if not gyr:
        return []
    q = integrate_gyro(np.stack(gyr, 1), np.stack([np.asarray(d, float) for d in dt], 1), np.stack(q0))
    return [q[:, s] for s in range(len(gyr))]


def nominal_levers(joints: list[BodyJoint], setups: dict[str, SensorSetup]) -> list[tuple[str, int, np.ndarray]]:
    """(sensor, joint index, s_l nominal) for both sides of every joint: s_l = sRb (b_joint − b_pos)."""
    out = []
    for j, jt in enumerate(joints):
        for seg, b_joint in ((jt.parent, jt.b_parent), (jt.child, jt.b_child)):
            st = setups[seg]
            out.append((seg, j, st.bRs_nom.T @ (b_joint - st.b_pos_nom)))
    return out


def initial_values(names: list[str], joints: list[BodyJoint], levers: list, nRs_kf: dict[str, np.ndarray],
                   kf_t: np.ndarray, setups: dict[str, SensorSetup], n_bias_seg: int = 1) -> gtsam.Values:
    """gtsam.Values for all keyframes: poses, velocities, biases, joint centres, lever arms."""
    K = kf_t.size
    idx = {n: i for i, n in enumerate(names)}
    pos = {names[0]: np.zeros((K, 3))}
    lever_of = {(seg, j): l for seg, j, l in levers}
    J = {}
    for j, jt in enumerate(joints):                  # topological: parents placed before children
        RP, RC = nRs_kf[jt.parent], nRs_kf[jt.child]
        J[j] = pos[jt.parent] + np.einsum("kij,j->ki", RP, lever_of[(jt.parent, j)])
        pos[jt.child] = J[j] - np.einsum("kij,j->ki", RC, lever_of[(jt.child, j)])
    vals = gtsam.Values()
    for name in names:
        s = idx[name]
        p = pos.get(name, np.zeros((K, 3)))           # no joints (ablation): at the origin
        v = np.gradient(p, kf_t, axis=0) if K > 1 else np.zeros_like(p)
        for k in range(K):
            vals.insert(bf.pose_key(s, k), gtsam.Pose3(gtsam.Rot3(nRs_kf[name][k]), p[k]))
            vals.insert(bf.vel_key(s, k), v[k])
        for m in range(n_bias_seg):                  # one bias per random-walk segment, all at the N-pose value
            vals.insert(bf.bias_key(s, m), gtsam.imuBias.ConstantBias(np.zeros(3), setups[name].gyro_bias0))
    for j in J:
        for k in range(K):
            vals.insert(bf.joint_key(j, k), J[j][k])
    for i, (_, _, l) in enumerate(levers):
        vals.insert(bf.lever_key(i), np.asarray(l, float))
    return vals



def find_npose(session, opts, min_rest_s: float = 1.0, min_after_s: float = 2.0) -> tuple[np.ndarray, str, dict]:
    """(N-pose sample indices, method, info): `body_model.npose_samples`, and where it has to assume one, the quietest
    common rest anywhere in the session (helper B23; `mocap --npose-search anywhere`).

    A user's recording may start moving (the N-pose cropped off, or recorded later). npose_samples then "assumes" the
    first MIN_REST samples to be the N-pose — moving ones — and the solve is garbage without a word. Here:
      - opts.npose given, or a common rest at the start ("given", "detected"): exactly npose_samples' answer;
      - else every run of common rest (all sensors' `detect_rest`) at least `min_rest_s` long and followed by at least
        `min_after_s` of data (the estimator needs motion after its N-pose: the real walk cropped by 12 s rests only in
        its last 1.8 s) is a candidate, and the quietest wins: the smallest   q = max_s median_{i in run} σ_gyr,s(i)   (σ_gyr: 0.5 s moving std of the gyro,
        root of the summed axis variances, as detect_rest); method "found";
      - no candidate: SessionError naming the session and the longest common rest seen, expecting --npose T0,T1.
    The estimator assumes its N-pose at the start of the data (initial orientations integrated from sample 0,
    estimate_placements over the keyframes up to the N-pose's end), so a caller uses a "found" window by solving the
    rows from its first sample on (info["start_row"]; `mocap` does).
    info: {"method", "t0", "t1" (s, session time), "start_row", "quiet_rad_s", "candidates"}."""
    from imugraph.calibration.rest import _moving_var, detect_rest
    from imugraph.graphs.body_model import npose_samples

    idx, method = npose_samples(session, opts)
    t = np.asarray(session.t, float)
    if method != "assumed":
        return idx, method, {"method": method, "t0": float(t[idx[0]]), "t1": float(t[idx[-1]]), "start_row": 0}
    rest, sig, per = np.ones(t.size, bool), [], {}
    for name, s in session.sensors.items():
        per[name] = detect_rest(s)
        rest &= per[name]
        n = max(3, int(round(0.5 * s.rate)))
        sig.append(np.sqrt(_moving_var(np.asarray(s.gyr, float), n).sum(axis=1)))
    edges = np.flatnonzero(np.diff(np.r_[0, rest.astype(int), 0]))
    runs = [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]              # [a, b) common rest
    longest = max(runs, key=lambda r: r[1] - r[0], default=None)
    good = [(a, b) for a, b in runs if t[b - 1] - t[a] >= min_rest_s and t[-1] - t[b - 1] >= min_after_s]
    if not good:
        seen = (f"the longest {t[longest[1] - 1] - t[longest[0]]:.2f} s at {t[longest[0]] - t[0]:.1f}–"
                f"{t[longest[1] - 1] - t[0]:.1f} s" if longest else "none") + _almost(per, t, min_rest_s, min_after_s)
        raise SessionError(session.source, "npose", f"no common rest of all {len(session.sensors)} sensors of at least "
                           f"{min_rest_s:g} s with {min_after_s:g} s of data after it ({seen})", "a standing rest (N-pose) to start from; give its "
                           "window in the session's time with --npose T0,T1 (BodyOptions.npose)")
    quiet = [float(max(np.nanmedian(g[a:b]) for g in sig)) for a, b in good]
    a, b = good[int(np.argmin(quiet))]
    return np.arange(a, b), "found", {"method": "found", "t0": float(t[a]), "t1": float(t[b - 1]), "start_row": a,
                                      "quiet_rad_s": float(min(quiet)),
                                      "candidates": [[float(t[x]), float(t[y - 1])] for x, y in good]}


def _almost(per: dict, t: np.ndarray, min_rest_s: float, min_after_s: float) -> str:
    """'; N of S sensors rest together for D s at T0–T1, not A, B' for the fewest sensors left out (≤ 3) that give a
    rest of min_rest_s, else '': which sensor keeps a session from having a common rest (find_npose's refusal)."""
    names = list(per)
    count = np.sum([per[n] for n in names], axis=0)
    for k in range(1, min(4, len(names))):
        edges = np.flatnonzero(np.diff(np.r_[0, (count >= len(names) - k).astype(int), 0]))
        runs = [(a, b) for a, b in zip(edges[::2], edges[1::2])
                if t[b - 1] - t[a] >= min_rest_s and t[-1] - t[b - 1] >= min_after_s]
        if runs:
            a, b = max(runs, key=lambda r: r[1] - r[0])
            out = [n for n in names if np.mean(per[n][a:b]) < 0.5]
            if not out:
                continue
            return (f"; {len(names) - len(out)} of {len(names)} sensors rest together for {t[b - 1] - t[a]:.1f} s at "
                    f"{t[a] - t[0]:.1f}–{t[b - 1] - t[0]:.1f} s, not {', '.join(out)}")
    return ""
