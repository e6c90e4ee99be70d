"""The field process chosen by held-out magnetometer prediction (imugraph.calibration.field_select)."""

from types import SimpleNamespace

import numpy as np
import pytest

from imugraph.calibration import field_select as fs
from imugraph.calibration.ml import Options, calibrate
from imugraph.io.session import Session
from imugraph.sim.scenario import distorted_session


def _rot(axis_angle):
    """Rodrigues' formula, written here independently of imugraph.geometry."""
    a = np.asarray(axis_angle, float)
    th = np.linalg.norm(a)
    k = a / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _quat(R):
    """w, x, y, z of a rotation matrix (trace form; the test rotations stay below 180°)."""
    w = 0.5 * np.sqrt(1.0 + np.trace(R))
    return np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])


def test_fold_masks_partition_time_blocks():
    t = np.arange(0, 10, 0.5)                            # 20 samples, blocks of 2 s = 4 samples
    masks = fs.fold_masks(t, 2.0, 3)
    assert np.all(np.sum(masks, axis=0) == 1)            # every sample held out exactly once
    block = np.repeat(np.arange(5), 4)
    for f, m in enumerate(masks):
        assert np.array_equal(m, block % 3 == f)
    with pytest.raises(ValueError):
        fs.fold_masks(t, 2.0, 1)


def test_held_out_errors_known_answer():
    rng = np.random.default_rng(3)
    n, stride = 40, 10
    t = np.arange(n) * 0.01
    D = np.array([[40.0, 1.0, -2.0], [0.5, 38.0, 1.5], [-1.0, 0.0, 45.0]])
    o = np.array([3.0, -5.0, 2.0])
    dip = np.deg2rad(60.0)
    n_nav = np.array([np.cos(dip), 0.0, -np.sin(dip)])
    d_k = rng.normal(0, 0.02, (4, 3))                     # keyframes at samples 0, 10, 20, 30
    R = [_rot(rng.normal(0, 1.0, 3)) for _ in range(n)]
    k_of = np.arange(n) // stride
    pert = np.zeros((n, 3))
    pert[25] = [0.4, -0.2, 0.1]                           # an error on one held-out sample, magnetometer units
    y = np.array([D @ R[i].T @ (n_nav + d_k[k_of[i]]) + o for i in range(n)]) + pert
    session = Session(t, np.zeros((n, 3)), np.tile([0, 0, 9.81], (n, 1)), y, name="known", source="known.npz")
    cal = SimpleNamespace(D=D, o=o, dip_deg=np.rad2deg(dip), mag_delay_s=0.0)
    est = SimpleNamespace(calibration=cal, quat=np.array([_quat(r) for r in R]),
                          info={"field_offsets": d_k, "keyframe_samples": np.arange(0, n, stride),
                                "disturbance_windows": [{"t_start": t[30], "t_end": t[34]}]})
    held = np.zeros(n, bool)
    held[20:35] = True
    e = fs.held_out_errors(session, est, held)
    assert e.shape == (10, 3)                              # 20..29 (30..34 are inside the window)
    expected = np.zeros((10, 3))
    expected[5] = R[25] @ np.linalg.solve(D, pert[25])
    assert np.allclose(e, expected, atol=1e-12)
    assert fs.score(e) == pytest.approx(min(np.sum(expected[5] ** 2), fs.HUBER_CLIP ** 2) / 10)


def test_choose_needs_a_significant_paired_gain():
    a, b = fs.Candidate(), fs.Candidate(tau_scale=3.0)
    ref = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    # b lower in every block by 0.1 ± 0.01: z = 0.1 / (std/√6), far above 2
    steady = {"candidate": b, "score": 3.4, "blocks": ref - 0.1 + 0.01 * np.array([1, -1, 1, -1, 1, -1])}
    table = [{"candidate": a, "score": 3.5, "blocks": ref}, steady]
    assert fs.choose(table, a, 2.0) == b
    d = 0.1 + 0.01 * np.array([1, -1, 1, -1, 1, -1])
    assert table[1]["z"] == pytest.approx(np.mean(d) / (np.std(d, ddof=1) / np.sqrt(6)))
    # the same mean gain carried by one block: mean 0.1, std 0.245, z = 1 → the reference is kept
    one = ref.copy()
    one[2] -= 0.6
    table = [{"candidate": a, "score": 3.5, "blocks": ref}, {"candidate": b, "score": 3.4, "blocks": one}]
    assert fs.choose(table, a, 2.0) == a
    assert table[1]["z"] == pytest.approx(1.0)
    bm = fs.block_means(np.array([1.0, 3.0, np.nan, 5.0, np.nan]), np.array([0, 0, 1, 2, 2]))
    assert np.allclose(bm[[0, 2]], [2.0, 5.0]) and np.isnan(bm[1])


def test_candidate_scales_the_configured_process():
    opt = Options(field_sigma=(0.01, 0.002, 0.01), field_tau=2.0, field_select=True)
    out = fs.Candidate((1.0, 2.0, 1.0), 3.0, gyro_map=False).apply(opt)
    assert out.field_sigma == pytest.approx((0.01, 0.004, 0.01))
    assert out.field_tau == pytest.approx(6.0)
    assert out.gyro_map is False and out.field_select is False
    assert opt.field_select is True and opt.field_tau == 2.0          # the input is not modified


def test_select_on_simulation_scores_the_noise_level():
    s, truth = distorted_session(11, duration_s=60, rate_hz=50)
    cands = (fs.Candidate(), fs.Candidate(tau_scale=3.0))
    best, table, _ = fs.select(s, Options(), cands, block_s=2.0, folds=2)
    # a constant field: the held-out error is the magnetometer noise (1 % of the field per axis, from the
    # simulator's settings, in magnetometer units: through D⁻¹ it is trace(D⁻¹ Σ D⁻ᵀ)) plus the orientation
    # error across a 2 s gap
    Dinv = np.linalg.inv(truth.D)
    expected = float(np.trace(Dinv @ np.diag(np.asarray(truth.noise["mag"]) ** 2) @ Dinv.T))
    for r in table:
        assert 0.8 * expected < r["score"] < 1.5 * expected, (r, expected)
    assert best in cands
    est = calibrate(s, Options(field_select=True))
    chosen = est.info["field_select"]
    assert chosen["chosen"] in [r["candidate"] for r in chosen["scores"]]
    assert len(chosen["scores"]) == len(fs.DEFAULT_CANDIDATES)
