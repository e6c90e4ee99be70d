"""Helpers of the body benchmarks: the over-seeds summary of body_sim_accuracy and the error analysis of
body_walk_diagnosis (known answers computed by hand, not by the code under test)."""

import numpy as np
import pytest

from benchmarks.body_sim_accuracy import SEED_COLUMNS, seed_summary
from benchmarks.body_walk_diagnosis import principal_rates, rate, time_structure
from imugraph.geometry import expmap


def _record(motion, seed, mag, joint_max, pos_rms, pos_worst, joint="LeftKnee", seg="Head"):
    return {"motion": motion, "seed": seed, "use_mag": mag, "lag_s": None,
            "row": {"joint_max_deg": joint_max, "worst_joint": joint, "pos_rms_cm": pos_rms,
                    "pos_worst_cm": pos_worst, "worst_segment": seg}}


def test_seed_summary_worst_over_seeds_and_targets():
    recs = [_record("a", 0, False, 0.5, 1.0, 2.0), _record("a", 1, False, 1.5, 0.5, 3.0, "Neck", "T8"),
            _record("a", 2, False, 1.0, 2.5, 1.0), _record("a", 0, True, 0.4, 0.4, 0.9)]
    rows = {r[0]: dict(zip(SEED_COLUMNS, r)) for r in seed_summary(recs)}
    no = rows["a no-mag"]
    assert no["seeds"] == 3
    assert no["joint max (°)"] == 1.5 and no["where"] == "s1 Neck"
    assert no["median joint max"] == pytest.approx(1.0)
    assert no["pos RMS max (cm)"] == 2.5 and no["median pos RMS"] == pytest.approx(1.0)
    assert no["worst segment (cm)"] == "3.00 T8"
    assert no["≤ 2°/2 cm"] == "NO"                  # seed 2's position RMS 2.5 cm breaks the target
    assert rows["a mag"]["≤ 2°/2 cm"] == "yes" and rows["a mag"]["seeds"] == 1


def test_time_structure_separates_drift_from_stride_errors():
    fs = 100.0
    t = np.arange(0, 10.0, 1 / fs)
    stride = 3.0 * np.sin(2 * np.pi * 0.7 * t)                      # phase-locked, 0.7 Hz
    ts = time_structure(stride, fs)
    assert ts["rms"] == pytest.approx(3.0 / np.sqrt(2), rel=0.02)
    assert ts["bands"]["0.4-1Hz"] == pytest.approx(3.0 / np.sqrt(2), rel=0.05)
    assert ts["bands"]["0-0.4Hz"] < 0.3
    # least-squares slope of A sin(ωt) over whole periods [0, T]: cov(t, e)/var(t) = (−A/ω)/(T²/12)
    assert ts["trend_deg_s"] == pytest.approx(-12 * 3.0 / (2 * np.pi * 0.7 * 10.0**2), rel=0.02)
    drift = time_structure(0.5 * t, fs)                              # 0.5 deg/s drift
    assert drift["trend_deg_s"] == pytest.approx(0.5, rel=1e-6)
    assert drift["bands"]["0-0.4Hz"] > 0.9 * drift["rms"]


def test_principal_rates_recover_a_hinge_axis():
    rng = np.random.default_rng(3)
    axis = np.array([0.1, 0.98, -0.17])
    axis /= np.linalg.norm(axis)
    angle = 0.8 * np.sin(np.linspace(0, 6 * np.pi, 600))            # flexion about a fixed axis
    R = expmap(angle[:, None] * axis)
    w = rate(R, 100.0)
    axes, rms = principal_rates(w + rng.normal(0, 1e-3, w.shape))
    assert abs(axes[:, 0] @ axis) > 0.9999
    assert rms[1] / rms[0] < 0.01                                    # a hinge: no second axis
    expected = np.sqrt(np.mean((np.diff(angle) * 100.0) ** 2))        # |ω| by hand
    assert rms[0] == pytest.approx(expected, rel=1e-3)


def test_axial_evidence_knee_turn_known_answer():
    """Thigh turned about its long axis by φ(t), shank flexed about y by κ(t), all else at rest: the knee-implied
    turn that puts the thigh's y on the shank's is −φ (v = Rz(−φ) y = (sin φ, cos φ, 0), by hand), so it
    correlates −1 with a thigh axial error of +φ, and its gain on the knee flexion is that of −φ on κ."""
    from benchmarks.body_walk_diagnosis import axial_evidence
    from imugraph.body.skeleton import lower_body
    from imugraph.geometry import rotmat_to_quat

    T = 400
    t = np.arange(T) / 100.0
    phi = np.deg2rad(5.0) * np.sin(2 * np.pi * 0.7 * t)
    kappa = np.deg2rad(30.0) * (1 + np.sin(2 * np.pi * 0.7 * t + 0.3))
    q = {n: np.tile([1.0, 0.0, 0.0, 0.0], (T, 1)) for n in lower_body().names}
    for side in ("Left", "Right"):
        q[f"{side}UpperLeg"] = rotmat_to_quat(expmap(phi[:, None] * np.array([0.0, 0.0, 1.0])))
        q[f"{side}LowerLeg"] = rotmat_to_quat(expmap(kappa[:, None] * np.array([0.0, 1.0, 0.0])))
        q[f"{side}Foot"] = rotmat_to_quat(expmap(np.deg2rad(3.0) * np.sin(2 * np.pi * 1.1 * t)[:, None]
                                                 * np.array([0.0, 0.0, 1.0])))
    seg_err = {n: np.zeros((T, 3)) for n in q}
    for side in ("Left", "Right"):
        seg_err[f"{side}UpperLeg"][:, 2] = np.rad2deg(phi)
        seg_err[f"{side}LowerLeg"][:, 2] = np.rad2deg(phi) * 0.5 + np.rad2deg(kappa) * 0.1
    out = axial_evidence({"imu_index": np.arange(T)}, q, 0, seg_err)
    v = out["Left"]
    assert v["knee_turn_rms"] == pytest.approx(np.rad2deg(phi).std(), rel=1e-3)
    assert v["corr_knee_turn_thigh_err"] == pytest.approx(-1.0, abs=1e-6)
    assert 0.5 < v["ankle_turn_rms"] < 3.0                # the foot's ±3° turn, seen through the flexed shank
    # gain of the thigh error (= +φ) on flexion, and of the knee turn (= −φ): opposite, equal size
    assert v["gain_knee_turn_on_flexion"] == pytest.approx(-v["gain_thigh_err_on_flexion"], rel=1e-3)
