"""Vectorised rotation helpers (numpy). Quaternions are w, x, y, z; `nRb` maps body to nav.

Right-perturbation convention as GTSAM: R ⊕ ξ = R · Exp(ξ).
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """(…, 3) → (…, 3, 3) cross-product matrices [v]×."""
    v = np.asarray(v, float)
    z = np.zeros(v.shape[:-1])
    return np.stack([
        np.stack([z, -v[..., 2], v[..., 1]], -1),
        np.stack([v[..., 2], z, -v[..., 0]], -1),
        np.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)


def expmap(w: np.ndarray) -> np.ndarray:
    """Rodrigues: (…, 3) rotation vectors → (…, 3, 3) rotation matrices."""
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * K + b * (K @ K)


def logmap(Rm: np.ndarray) -> np.ndarray:
    """(…, 3, 3) rotation matrices → (…, 3) rotation vectors (via quaternions, robust near π)."""
    q = rotmat_to_quat(Rm)
    return quat_to_rotvec(q)


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_continuous(q: np.ndarray) -> np.ndarray:
    """Quaternions (T, …, 4) with signs flipped along axis 0 so consecutive samples lie in the same
    hemisphere (q_k · q_{k−1} ≥ 0): sign_k = sign_{k−1} · (−1 where q_k · q_{k−1} < 0), sign_0 = +1."""
    q = np.array(q, float)
    flip = np.sum(q[1:] * q[:-1], axis=-1) < 0                          # (T−1, …) sign changes
    sign = np.concatenate([np.ones((1,) + flip.shape[1:]), np.cumprod(np.where(flip, -1.0, 1.0), axis=0)])
    return q * sign[..., None]


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(…, 4) w,x,y,z → (…, 3, 3)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def rotmat_to_quat(Rm: np.ndarray) -> np.ndarray:
    """(…, 3, 3) → (…, 4) w,x,y,z with w ≥ 0 (Shepperd's method, vectorised)."""
    Rm = np.asarray(Rm, float)
    m00, m11, m22 = Rm[..., 0, 0], Rm[..., 1, 1], Rm[..., 2, 2]
    tr = m00 + m11 + m22
    cands = np.stack([
        np.stack([1 + tr, Rm[..., 2, 1] - Rm[..., 1, 2], Rm[..., 0, 2] - Rm[..., 2, 0], Rm[..., 1, 0] - Rm[..., 0, 1]], -1),
        np.stack([Rm[..., 2, 1] - Rm[..., 1, 2], 1 + m00 - m11 - m22, Rm[..., 0, 1] + Rm[..., 1, 0], Rm[..., 0, 2] + Rm[..., 2, 0]], -1),
        np.stack([Rm[..., 0, 2] - Rm[..., 2, 0], Rm[..., 0, 1] + Rm[..., 1, 0], 1 - m00 + m11 - m22, Rm[..., 1, 2] + Rm[..., 2, 1]], -1),
        np.stack([Rm[..., 1, 0] - Rm[..., 0, 1], Rm[..., 0, 2] + Rm[..., 2, 0], Rm[..., 1, 2] + Rm[..., 2, 1], 1 - m00 - m11 + m22], -1),
    ], -2)
    diag = np.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    idx = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, idx[..., None, None], axis=-2)[..., 0, :]
    return quat_normalize(q)


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p ⊗ q, (…, 4)."""
    pw, px, py, pz = np.moveaxis(np.asarray(p, float), -1, 0)
    qw, qx, qy, qz = np.moveaxis(np.asarray(q, float), -1, 0)
    return np.stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ], -1)


def quat_conj(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between unit quaternions (…, 4): 2 arccos |⟨a, b⟩| (either sign of a quaternion)."""
    return 2.0 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0))


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    q = quat_normalize(q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    ang = 2.0 * np.arctan2(s, q[..., 0])
    scale = np.where(s < 1e-12, 2.0, ang / np.where(s < 1e-12, 1.0, s))
    return v * scale[..., None]


def rotvec_to_quat(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1, keepdims=True)
    half = 0.5 * th
    k = np.where(th < 1e-12, 0.5, np.sin(half) / np.where(th < 1e-12, 1.0, th))
    return np.concatenate([np.cos(half), w * k], -1)


def quat_slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Vectorised slerp between (…, 4) arrays with fraction u (…,)."""
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    d = np.sum(q0 * q1, -1)
    q1 = np.where(d[..., None] < 0, -q1, q1)
    rel = quat_mul(quat_conj(q0), q1)
    return quat_mul(q0, rotvec_to_quat(np.asarray(u)[..., None] * quat_to_rotvec(rel)))


def integrate_gyro(gyr: np.ndarray, dt: np.ndarray, q0: np.ndarray | None = None) -> np.ndarray:
    """Strapdown integration q_{k+1} = q_k ⊗ Exp(ω_k dt_k): (N, 4) with q[0] = q0.

    Sequential (a cumulative product); fast enough for 10⁵ samples in numpy via rotation matrices. Several
    sensors at once: gyr (N, S, 3), dt (N, S), q0 (S, 4) → (N, S, 4), each sensor bit for bit its own call.
    """
    n = gyr.shape[0]
    dq = rotvec_to_quat(gyr * np.asarray(dt)[..., None])
    out = np.empty(gyr.shape[:-1] + (4,))
    out[0] = np.array([1.0, 0, 0, 0]) if q0 is None else quat_normalize(q0)
    # Chunked cumulative product keeps it vectorised where possible.
    q = out[0]
    for k in range(1, n):
        q = quat_mul(q, dq[k - 1])
        out[k] = q
    return quat_normalize(out)
