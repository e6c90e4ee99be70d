"""Shared set-up of the body benchmarks (issue 4a, 4c): simulated 17-IMU sessions from real motions.

Motions (read from the data directory, $IMUGRAPH_DATA or ../shared/data; nothing copied):
    cmu131_01, cmu131_02   cmu_bvh/scaled_131_0{1,2}.bvh (CMU, 120 Hz, metres; 21 MVN segments, no L3/T12)
    xsens                  gaittoolbox/xsens/S02-Trial-Walk-1.bvh (Xsens MVN export, 23 segments)
Each is turned into segment trajectories by `imugraph.sim.body.motion_from_bvh` (a 2 s static N-pose, a 1 s
blend into the first frame, resampled to 60 Hz) and 17 IMUs are placed at random on their segments
(`random_placements`: up to 30° and 3 cm off the nominal site), then simulated with one `SensorParams` per
sensor. Sensor errors ("realistic": the Xsens MTw of the gaittoolbox sample, measured on its feet standing
still for 7 s at 100 Hz: gyro σ ≈ 0.002 rad/s, acc σ ≈ 0.015 m/s², field σ ≈ 0.003 of |m|; rest gyro means up
to 0.03 rad/s): gyro noise σ 0.003 rad/s, accelerometer noise σ 0.02 m/s², gyro bias N(0, 0.01 rad/s) per
axis, accelerometer bias N(0, 0.05 m/s²) per axis, magnetometer (calibrated, unit field, dip 60°) noise
σ 0.005. Scores (imugraph.body.evaluate) are taken over the BVH motion only (t ≥ N-pose + blend). By default
the unsensed segments move as in the BVH (the estimator ties them to their neighbours, so their positions
carry that model error); `tie=True` makes the truth follow the ties.
"""

from __future__ import annotations

import sys
from dataclasses import fields
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from imugraph.body.skeleton import LOWER_BODY  # noqa: E402
from imugraph.config import data_dir  # noqa: E402

MOTIONS = {"cmu131_01": "cmu_bvh/scaled_131_01.bvh", "cmu131_02": "cmu_bvh/scaled_131_02.bvh",
           "xsens": "gaittoolbox/xsens/S02-Trial-Walk-1.bvh"}
RATE_HZ, NPOSE_S, BLEND_S = 60.0, 2.0, 1.0
NOISE = {"gyro_noise": 0.003, "acc_noise": 0.02, "gyro_bias": 0.01, "acc_bias": 0.05, "mag_noise": 0.005}


def motion_path(name: str) -> Path:
    return data_dir() / MOTIONS[name]


def sensor_params(names, rng):
    """One SensorParams per sensor with the module's noise and freshly drawn biases."""
    from imugraph.sim.sensors import SensorParams

    return {n: SensorParams(gyro_bias=rng.normal(0.0, NOISE["gyro_bias"], 3),
                            gyro_noise=np.full(3, NOISE["gyro_noise"]), acc_noise=np.full(3, NOISE["acc_noise"]),
                            acc_bias=rng.normal(0.0, NOISE["acc_bias"], 3), mag_noise=np.full(3, NOISE["mag_noise"]),
                            dip_rad=float(np.deg2rad(60.0))) for n in names}


def add_bias_walk(session, sigma: float, rng):
    """The session with a gyro bias random walk added to every sensor, starting at 0 at t = 0:

        b_k = b_{k−1} + w_k,   w_k ~ N(0, σ² Δt I)      (σ in rad/s/√s)

    so the bias the N-pose rest sees is the constant one, and it wanders afterwards (temperature, turn-on drift).
    """
    from dataclasses import replace

    if not sigma:
        return session
    sensors = {}
    for n, s in session.sensors.items():
        dt = np.diff(s.t, prepend=s.t[0])[:, None]
        walk = np.cumsum(rng.standard_normal(s.gyr.shape) * sigma * np.sqrt(dt), axis=0)
        sensors[n] = replace(s, gyr=s.gyr + walk)
    return replace(session, sensors=sensors, meta=dict(session.meta, gyro_bias_walk=sigma))


def simulated_session(name: str, seed: int = 0, duration_s: float | None = None, lower: bool = False,
                      skip_s: float | None = None, tie: bool = False, bias_walk: float = 0.0):
    """(skeleton, BodySession with truth, scoring mask) for one motion (module docstring).

    tie: the truth's unsensed segments (spine links, neck, toes) follow the estimator's ties (K2) instead of
    the BVH (imugraph.sim.body.motion_from_bvh tie_unsensed): removes the model error of the ties.
    bias_walk: gyro bias random walk σ, rad/s/√s (`add_bias_walk`; 0: constant biases only).
    """
    from imugraph.sim.body import BodyMotion, motion_from_bvh, random_placements, simulate_body

    skel, motion = motion_from_bvh(motion_path(name), rate_hz=RATE_HZ, npose_s=NPOSE_S, blend_s=BLEND_S,
                                   duration_s=duration_s, skip_s=skip_s, tie_unsensed=tie)
    if lower:
        idx = [skel.index(n) for n in LOWER_BODY]
        skel = skel.subset(LOWER_BODY)
        motion = BodyMotion(motion.t, skel.names, motion.n_quat[:, idx], motion.n_pos[:, idx])
    rng = np.random.default_rng(seed)
    placements = random_placements(skel, rng, max_angle_deg=30.0, max_shift_m=0.03)
    session = simulate_body(motion, skel, placements, sensor_params(list(placements), rng), rng,
                            name=f"{name}_seed{seed}")
    session = add_bias_walk(session, bias_walk, rng)
    mask = session.t >= NPOSE_S + BLEND_S - 1e-9
    return skel, session, mask


def option_fields() -> set:
    from imugraph.graphs.body_model import BodyOptions

    return {f.name for f in fields(BodyOptions)}


def ablation_options(variant: str, **base):
    """BodyOptions for an ablation variant: 'full', 'no_joints', 'no_levers'.

    no_joints: BodyOptions.use_joints=False (the estimator then also has no lever arms: independent sensors);
    without that option, joint σ 1 km. no_levers: the lever-arm priors (sensor-to-segment position factors)
    dropped, lever_sigma_m=None (use_levers=False if the estimator has it; else σ 1 km). Returns (options, how).
    """
    from imugraph.graphs.body_model import BodyOptions

    have = option_fields()
    kw, how = dict(base), []
    if variant == "no_joints":
        if "use_joints" in have:
            kw["use_joints"], how = False, how + ["use_joints=False"]
        else:
            kw.update(joint_sigma_m=1e3, lumped_joint_sigma_m=1e3)
            how.append("joint σ 1e3 m (no use_joints option)")
    if variant == "no_levers":
        if "use_levers" in have:
            kw["use_levers"], how = False, how + ["use_levers=False"]
        elif "None" in str(BodyOptions.__dataclass_fields__["lever_sigma_m"].type):
            kw["lever_sigma_m"], how = None, how + ["lever_sigma_m=None"]
        else:
            kw["lever_sigma_m"] = 1e3
            how.append("lever prior σ 1e3 m")
    return BodyOptions(**kw), ", ".join(how) or "defaults"


# the columns of summary_row's table, in print order
SUMMARY_COLUMNS = ["case", "joint_max_deg", "worst_joint", "joint_mean_deg", "pos_rms_cm", "pos_worst_cm",
                   "worst_segment", "solve_s"]


def summary_row(label: str, scores: dict, seconds: float) -> dict:
    """One table row: worst and mean joint RMSE (deg), relative position RMS and worst segment (cm), time."""
    j = scores["joints"]
    worst = max(j, key=lambda k: j[k]["all"])
    pos = scores["position"]
    return {"case": label, "joint_max_deg": j[worst]["all"], "worst_joint": worst,
            "joint_mean_deg": float(np.mean([v["all"] for v in j.values()])),
            "pos_rms_cm": 100 * pos["rms_m"], "pos_worst_cm": 100 * max(pos["per_segment"].values()),
            "worst_segment": pos["max_segment"], "solve_s": seconds}
