"""Body-session diagnosis (imugraph.diagnose.body): residuals, gap near zero on data from the model, the oscillator
against its closed form, the CLI dispatch (attribution: tests/test_diagnose_body_attribution.py).

Sessions are simulated here from an analytic lower-body motion (independent of the BVH data): a static N-pose,
then sinusoidal hip/knee/ankle flexion blended in and the pelvis walking forward at 1 m/s with a vertical bob.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from imugraph.body.skeleton import lower_body
from imugraph.diagnose.body.effects.soft_tissue import oscillator
from imugraph.diagnose.body.fit import fit_body, joint_acceleration
from imugraph.diagnose.body.gap import model_sigma, sensor_gaps
from imugraph.diagnose.body.simulate import fit_simulation, simulate_from_fit
from imugraph.geometry import expmap, rotmat_to_quat
from imugraph.sim.body import BodyMotion, random_placements, simulate_body
from imugraph.sim.sensors import SensorParams

RATE = 60.0


def _motion(duration_s: float, seed: int = 0):
    """Lower-body motion: joint flexion θ_j(t) = A_j env(t) sin(2π f t + φ_j) about each segment's y axis
    (nRb_child = nRb_parent · Exp(θ e_y)), pelvis yaw fixed, root p = (v t_w, 0, 0.95 + 0.02 sin(4π f t))."""
    rng = np.random.default_rng(seed)
    skel = lower_body()
    t = np.arange(0.0, duration_s, 1.0 / RATE)
    u = np.clip(t - 2.0, 0.0, 1.0)
    env = u * u * (3 - 2 * u)
    f = 0.9
    amp = {"RightUpperLeg": 30, "LeftUpperLeg": 30, "RightLowerLeg": 35, "LeftLowerLeg": 35,
           "RightFoot": 15, "LeftFoot": 15}
    S = len(skel.names)
    R = np.zeros((t.size, S, 3, 3))
    for i, name in enumerate(skel.names):
        p = skel.parents[i]
        if p < 0:
            R[:, i] = expmap(np.stack([np.zeros_like(t), 0.05 * env * np.sin(2 * np.pi * f * t),
                                       0.1 * env * np.sin(2 * np.pi * f * t + 1.0)], axis=1))
            continue
        ph = (np.pi if name.startswith("Left") else 0.0) + rng.uniform(-0.3, 0.3)
        th = np.deg2rad(amp[name]) * env * np.sin(2 * np.pi * f * t + ph)
        side = 0.1 * env * np.sin(2 * np.pi * f * t + ph + 0.5)
        R[:, i] = R[:, p] @ expmap(np.stack([side, th, 0.3 * side], axis=1))
    q = rotmat_to_quat(R)
    tw = np.cumsum(env) / RATE
    root = np.stack([1.0 * tw, np.zeros_like(t), 0.95 + 0.02 * env * np.sin(4 * np.pi * f * t)], axis=1)
    return skel, BodyMotion(t, skel.names, q, skel.forward_kinematics(q, root))


def _session(duration_s: float = 14.0, seed: int = 0, noise: bool = True):
    skel, motion = _motion(duration_s, seed)
    rng = np.random.default_rng(seed + 10)
    pl = random_placements(skel, rng, max_angle_deg=20.0, max_shift_m=0.02)
    prm = SensorParams(gyro_noise=np.full(3, 0.003 if noise else 0.0), acc_noise=np.full(3, 0.02 if noise else 0.0),
                       gyro_bias=rng.normal(0, 0.005, 3) if noise else np.zeros(3))
    return simulate_body(motion, skel, pl, prm, rng, name=f"synth{seed}")


def test_oscillator_matches_closed_form_step_response():
    """(ST1) against the analytic step response of x'' + 2ζω x' + ω² x = ω² u (computed here, not by scipy)."""
    dt, fn, z = 1 / 100, 7.0, 0.3
    t = np.arange(0, 3, dt)
    u = np.zeros((t.size, 3))
    u[t >= 0.5, 1] = 2.0
    x, xd, xdd = oscillator(u, dt, fn, z)
    w, tt = 2 * np.pi * fn, t[t >= 0.5] - 0.5
    wd = w * np.sqrt(1 - z * z)
    xa = 2.0 * (1 - np.exp(-z * w * tt) * (np.cos(wd * tt) + z / np.sqrt(1 - z * z) * np.sin(wd * tt)))
    xda = 2.0 * np.exp(-z * w * tt) * (w / np.sqrt(1 - z * z)) * np.sin(wd * tt)
    assert np.max(np.abs(x[t >= 0.5, 1] - xa)) < 1e-9
    assert np.max(np.abs(xd[t >= 0.5, 1] - xda)) < 1e-8
    assert np.allclose(x[:, [0, 2]], 0) and np.allclose(x[t < 0.5, 1], 0)
    assert np.allclose(xdd, w * w * (u - x) - 2 * z * w * xd)


def test_joint_acceleration_agrees_across_a_joint_on_noiseless_rigid_motion():
    """(BR4) with the TRUE orientations and levers of a noiseless simulation: both sensors of a joint see the
    same joint-centre acceleration (up to the discretisation of ω̇ at 60 Hz), while a 2 cm lever error does not."""
    bs = _session(8.0, seed=3, noise=False)
    tr, skel = bs.truth, bs.skeleton
    from imugraph.geometry import quat_to_rotmat
    i_p, i_c = skel.index("RightUpperLeg"), skel.index("RightLowerLeg")
    n_knee = tr["n_pos"][:, i_c]                                                  # joint centre = child origin
    out = {}
    for name, i in (("RightUpperLeg", i_p), ("RightLowerLeg", i_c)):
        s = bs.sensors[name]
        R = quat_to_rotmat(s.quat)
        lever = np.einsum("ba,b->a", R[200], n_knee[200] - tr["sensor_pos"][name][200])   # constant on a rigid body
        out[name] = (R, s, lever)
    jac = {n: np.einsum("nab,nb->na", R, joint_acceleration(s.t, s.gyr, s.acc, 0.0, 0.0, lev))
           for n, (R, s, lev) in out.items()}
    moving = bs.t > 3.5
    err = np.linalg.norm(jac["RightUpperLeg"] - jac["RightLowerLeg"], axis=1)[moving][5:-5]
    R, s, lev = out["RightUpperLeg"]
    wrong = np.einsum("nab,nb->na", R, joint_acceleration(s.t, s.gyr, s.acc, 0.0, 0.0, lev + [0.02, 0, 0]))
    err_wrong = np.linalg.norm(wrong - jac["RightLowerLeg"], axis=1)[moving][5:-5]
    assert np.sqrt(np.mean(err**2)) < 0.05
    assert np.sqrt(np.mean(err_wrong**2)) > 2 * np.sqrt(np.mean(err**2))


def test_gap_is_near_zero_on_data_from_the_fitted_model():
    """A simulation of the fitted model, diagnosed like a recording: its gap (real = simulation C) is at the
    level of the noise floor on every sensor × channel (ratio gap_raw / null ≤ 2.5, as the single-IMU rule's 2)."""
    real = fit_body(_session(11.0, seed=0))
    rng = np.random.default_rng(1)
    c = fit_simulation(simulate_from_fit(real, rng, "+C"), real)
    a = fit_simulation(simulate_from_fit(real, rng, "+A"), real)
    b = fit_simulation(simulate_from_fit(real, rng, "+B"), real)
    g = sensor_gaps(c, a, b, model_sigma(a))
    ratios = {(n, ch): v["gap_raw"] / max(v["null_gap"], 1e-9) for n, d in g.items() for ch, v in d.items()
              if v["null_gap"] > 0}
    assert max(ratios.values()) < 2.5, sorted(ratios.items(), key=lambda kv: -kv[1])[:3]


def test_cli_dispatches_body_folders(tmp_path):
    """`imugraph diagnose FOLDER` on a body-session folder runs the body diagnosis (own format round trip)."""
    from imugraph.cli import main
    from imugraph.io.body_session import write_body_session

    bs = _session(9.0, seed=5)
    folder = tmp_path / "body"
    write_body_session(folder, bs)
    rc = main(["diagnose", str(folder), "--out", str(tmp_path / "out"), "--quiet", "--effects", "soft_tissue"])
    assert rc == 0
    js = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert js["base_model"]["kind"] == "body" and set(js["gap_per_sensor"]) == set(bs.sensors)
    assert {e["name"] for e in js["effects"]} == {"soft_tissue"}
