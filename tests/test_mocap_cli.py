"""`imugraph mocap` (imugraph.commands.mocap) and the body figures: files, contracts, errors."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from imugraph.body.skeleton import LOWER_BODY, lower_body
from imugraph.commands.mocap import add_arguments, hinge_segments, run_mocap
from imugraph.errors import SessionError
from imugraph.geometry import expmap, rotmat_to_quat
from imugraph.io.body_figures import plot_joint_angles, plot_stick_figures


def _args(argv):
    p = argparse.ArgumentParser()
    add_arguments(p)
    return p.parse_args(argv)


@pytest.fixture(scope="module")
def sim_folder(tmp_path_factory):
    """A 4 s lower-body session simulated by imugraph.sim.body from analytic joint motion, written to a folder."""
    from imugraph.io.body_session import write_body_session
    from imugraph.sim.body import BodyMotion, random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    skel = lower_body()
    rate, T = 60.0, 240
    t = np.arange(T) / rate
    env = np.clip((t - 1.5) / 1.0, 0, 1) ** 2
    R = np.zeros((T, len(skel.names), 3, 3))
    R[:, 0] = expmap(np.stack([0.05 * env * np.sin(2 * t), 0.05 * env * np.sin(3 * t), 0.3 * env * np.sin(t)], -1))
    for i in range(1, len(skel.names)):
        w = np.stack([0.1 * np.sin(1.7 * t + i), 0.5 * np.sin(2.5 * t + 0.7 * i), 0.1 * np.sin(1.3 * t)], -1)
        R[:, i] = R[:, skel.parents[i]] @ expmap(env[:, None] * w)
    q = rotmat_to_quat(R)
    root = np.stack([0.2 * env * np.sin(t), 0.1 * env * np.sin(0.7 * t), 0.93 + 0 * t], -1)
    motion = BodyMotion(t=t, names=skel.names, n_quat=q, n_pos=skel.forward_kinematics(q, root))
    rng = np.random.default_rng(0)
    prm = SensorParams(gyro_noise=np.full(3, 0.003), acc_noise=np.full(3, 0.03), mag_noise=np.full(3, 0.01))
    session = simulate_body(motion, skel, random_placements(skel, rng, max_angle_deg=20), prm, rng, name="mini")
    folder = tmp_path_factory.mktemp("body") / "mini"
    write_body_session(folder, session)
    return folder


@pytest.fixture(scope="module")
def mocap_out(sim_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("mocap_out")
    code = run_mocap(_args([str(sim_folder), "--out", str(out), "--quiet"]))
    return code, out


def test_mocap_writes_contract_files(mocap_out):
    code, out = mocap_out
    assert code == 0
    for name in ("mocap.npz", "joint_angles.csv", "motion.bvh", "joint_angles.png", "stick_figures.png",
                 "mocap_info.json"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert not list(out.glob(".*.tmp"))
    z = np.load(out / "mocap.npz")
    T = z["t"].size
    assert list(z["segments"]) == list(LOWER_BODY)
    assert z["quat"].shape == (T, 7, 4) and z["pos"].shape == (T, 7, 3) and T == 240
    assert np.allclose(np.linalg.norm(z["quat"], axis=-1), 1.0, atol=1e-9)
    # joint centres coincide: each child origin = parent origin + nRb_parent · offset (forward kinematics)
    skel = lower_body()
    from imugraph.geometry import quat_to_rotmat
    R = quat_to_rotmat(z["quat"])
    for i in range(1, 7):
        p = skel.parents[i]
        assert np.allclose(z["pos"][:, i], z["pos"][:, p] + R[:, p] @ skel.offsets[i], atol=1e-9)
    info = json.loads((out / "mocap_info.json").read_text())
    assert info["solver"] == "batch" and info["hinges"] == []
    assert info["scores"] is not None and "RightKnee" in info["scores"]["joints"]


def test_joint_angles_csv_and_bvh_round_trip(mocap_out):
    from imugraph.body.angles import joint_angles
    from imugraph.body.bvh_map import segment_motion

    _, out = mocap_out
    z = np.load(out / "mocap.npz")
    lines = (out / "joint_angles.csv").read_text().splitlines()
    head = lines[0].split(",")
    assert head[:4] == ["t", "RightHip_flexion", "RightHip_abduction", "RightHip_rotation"]
    table = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    assert table.shape == (z["t"].size, 1 + 3 * 6)
    ang = joint_angles(lower_body(), z["quat"])
    assert np.allclose(table[:, head.index("LeftKnee_flexion")], ang["LeftKnee"][:, 0], atol=1e-4, rtol=1e-5)
    skel_b, _, _, q_b, p_b = segment_motion(out / "motion.bvh")
    assert list(skel_b.names) == list(LOWER_BODY)
    dots = np.abs(np.sum(q_b * z["quat"], axis=-1))                     # same rotations (up to sign)
    assert np.all(dots > 1 - 1e-8)
    assert np.allclose(p_b[:, 0], z["pos"][:, 0], atol=1e-5)


def test_mocap_errors(sim_folder, tmp_path):
    with pytest.raises(SessionError):
        run_mocap(_args([str(tmp_path / "absent"), "--out", str(tmp_path / "o"), "--quiet"]))
    with pytest.raises(SessionError):
        run_mocap(_args([str(sim_folder), "--out", str(tmp_path / "o"), "--quiet", "--hinges", "wrists"]))
    with pytest.raises(SessionError):
        run_mocap(_args([str(sim_folder), "--out", str(tmp_path / "o"), "--quiet", "--lag", "-1"]))


def test_hinge_segments():
    skel = lower_body()
    assert hinge_segments("knees", skel) == ("RightLowerLeg", "LeftLowerLeg")
    assert hinge_segments("knees,elbows", skel) == ("RightLowerLeg", "LeftLowerLeg")     # no arms: skipped
    assert hinge_segments("LeftKnee, RightLowerLeg", skel) == ("LeftLowerLeg", "RightLowerLeg")
    assert hinge_segments("", skel) == ()
    with pytest.raises(SessionError):
        hinge_segments("RightElbow", skel)


def test_cli_dispatch_when_wired(sim_folder, tmp_path):
    from imugraph import cli

    if "mocap" not in cli.COMMANDS:
        pytest.skip("mocap not yet wired into imugraph.cli")
    assert cli.main(["mocap", str(tmp_path / "absent"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert cli.main(["mocap", "--help"]) == 0


def test_figures_shapes_and_errors(tmp_path):
    skel = lower_body()
    T = 50
    t = np.arange(T) / 50.0
    q = np.tile([1.0, 0, 0, 0], (T, 7, 1))
    pos = skel.forward_kinematics(q, np.tile([0, 0, 0.9], (T, 1)))
    angles = {"RightKnee": np.zeros((T, 3)), "LeftKnee": np.ones((T, 3)), "Trunk": np.zeros((T, 3))}
    plot_joint_angles(tmp_path / "a.png", t, angles, reference=angles)
    plot_stick_figures(tmp_path / "s.png", skel, t, q, pos, count=3)
    assert (tmp_path / "a.png").stat().st_size > 1000 and (tmp_path / "s.png").stat().st_size > 1000
    with pytest.raises(SessionError):
        plot_joint_angles(tmp_path / "b.png", t, {"RightKnee": np.zeros((T - 1, 3))})
    with pytest.raises(SessionError):
        plot_stick_figures(tmp_path / "c.png", skel, t, q[:, :3], pos)
    assert not (tmp_path / "b.png").exists() and not (tmp_path / "c.png").exists()


def test_mocap_fixed_lag_writes_timing(sim_folder, tmp_path):
    pytest.importorskip("imugraph.graphs.body_incremental")
    out = tmp_path / "lag"
    assert run_mocap(_args([str(sim_folder), "--out", str(out), "--quiet", "--lag", "1.0"])) == 0
    timing = json.loads((out / "timing.json").read_text())
    assert timing["updates"] >= 1 and timing["p99_ms"] >= timing["p50_ms"] > 0 and timing["realtime_factor"] > 0
    for name in ("mocap.npz", "mocap_filtered.npz"):
        z = np.load(out / name)
        assert z["quat"].shape == (240, 7, 4) and list(z["segments"]) == list(LOWER_BODY)
    assert json.loads((out / "mocap_info.json").read_text())["solver"] == "fixed_lag 1 s"
