"""stream_realign: the rotation about the field re-solved from integrated specific force (eq. R1–R3)."""

import gtsam
import numpy as np

from imugraph.graphs.stream_realign import GapRealign, anchor_factor


def _field(dip_deg: float) -> np.ndarray:
    d = np.radians(dip_deg)
    return np.array([np.cos(d), 0.0, -np.sin(d)])


def _window(nRg_true: np.ndarray, rng, n_int: int = 10, dt: float = 0.1, v_change=np.zeros(3)) -> GapRealign:
    """A window of n_int intervals with random turns; Δv_j in keyframe j's frame from the true attitude:
    nR_j Δv_j = g Δt e_z + (velocity change)/n_int (R1 inverted)."""
    w = GapRealign(n_int * dt)
    nRj = nRg_true.copy()
    for _ in range(n_int):
        dR = gtsam.Rot3.Expmap(rng.normal(0, 0.3, 3)).matrix()
        dv_n = np.array([0.0, 0.0, 9.81 * dt]) + np.asarray(v_change) / n_int
        w.add(nRj.T @ dv_n, dR, dt)
        nRj = nRj @ dR
    w.nR_end_true = nRj
    return w


def test_alpha_recovers_a_rotation_about_the_field():
    rng = np.random.default_rng(3)
    n = _field(71.6)
    for alpha_true in (np.radians(142.0), np.radians(-60.0), np.radians(5.0)):
        nRg = gtsam.Rot3.Expmap(rng.normal(0, 1.0, 3)).matrix()
        w = _window(nRg, rng)
        # the estimate is off by a rotation of −α_true about n̂: Exp(α* n̂)·R̂ must give back the truth
        R_pred = gtsam.Rot3.Expmap(-alpha_true * n).matrix() @ w.nR_end_true
        alpha, sig = w.solve(R_pred, n, 0.5)
        assert abs(np.degrees(alpha - alpha_true)) < 1e-6
        # (R3): √2 σ_v / |u⊥|, |u⊥| = g W cos(dip)
        assert np.isclose(sig, np.sqrt(2) * 0.5 / (9.81 * 1.0 * np.cos(np.radians(71.6))), rtol=1e-6)


def test_alpha_error_from_a_velocity_change_is_within_sigma():
    rng = np.random.default_rng(4)
    n = _field(60.0)
    nRg = gtsam.Rot3.Expmap(rng.normal(0, 1.0, 3)).matrix()
    w = _window(nRg, rng, v_change=np.array([0.5, -0.5, 0.0]))     # |Δv| = √2 σ_v, σ_v = 0.5
    alpha, sig = w.solve(w.nR_end_true, n, 0.5)
    assert abs(alpha) <= 1.01 * sig


def test_anchor_constrains_only_the_field_axis():
    n = _field(71.6)
    R = gtsam.Rot3.Expmap(np.array([0.3, -0.2, 1.0])).matrix()
    f = anchor_factor(1, R, np.zeros(3), n, 0.0, np.radians(1.0))
    v = gtsam.Values()
    off_axis = np.cross(n, [0.0, 1.0, 0.0])
    off_axis /= np.linalg.norm(off_axis)
    v.insert(1, gtsam.Pose3(gtsam.Rot3(gtsam.Rot3.Expmap(0.5 * off_axis).matrix() @ R), np.array([3.0, 0, 0])))
    assert f.error(v) < 1e-6                      # a turn across the field and any position: free
    v.update(1, gtsam.Pose3(gtsam.Rot3(gtsam.Rot3.Expmap(np.radians(2.0) * n).matrix() @ R), np.zeros(3)))
    assert np.isclose(f.error(v), 0.5 * 2.0**2, rtol=1e-3)    # 2σ about n̂: ½ r²
