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

