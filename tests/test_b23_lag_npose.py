"""Helper B23 (issue 4): the fixed lag's start uses only the rows its bootstrap has (BodyOptions.lag_init_causal,
body_lag_boot.causal_start (C1)), and sessions that start moving (body_init.find_npose, `mocap --npose-search anywhere`).

Simulated from the Xsens MVN walk and CMU 131_01 in the data directory (skipped without them); the truths are the
simulator's, never the estimator's."""

import dataclasses
import json

import numpy as np
import pytest

from imugraph.config import data_dir

BVH = "gaittoolbox/xsens/S02-Trial-Walk-1.bvh"
CMU = "cmu_bvh/scaled_131_01.bvh"


def _sim(path, duration_s=None, turn=False, seed=3):
    from imugraph.body.placement import Placement
    from imugraph.graphs.body_init import rz
    from imugraph.sim.body import motion_from_bvh, random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    if not (data_dir() / path).exists():
        pytest.skip(f"{path} absent")
    skel, mo = motion_from_bvh(data_dir() / path, rate_hz=60.0, npose_s=2.0, blend_s=1.0, duration_s=duration_s)
    rng = np.random.default_rng(seed)
    place = random_placements(skel, rng, max_angle_deg=30.0, max_shift_m=0.03)
    if turn:              # a suit strapped on another way: init "auto" switches most sensors
        place = {n: Placement(bRs=rz(rng.uniform(0.0, 2 * np.pi)) @ p.bRs, b_pos=p.b_pos) for n, p in place.items()}
    prm = {n: SensorParams(gyro_bias=rng.normal(0.0, 0.01, 3), gyro_noise=np.full(3, 0.003),
                           acc_noise=np.full(3, 0.02), acc_bias=rng.normal(0.0, 0.05, 3)) for n in place}
    return skel, mo, place, prm, rng


def _garbage_after(bs, cut):
    """Rows [cut:] of every sensor replaced by random finite values (cut None: contiguous copies, same rows)."""
    rng, out = np.random.default_rng(0), {}
    for n, s in bs.sensors.items():
        gyr, acc = s.gyr.copy(), s.acc.copy()
        if cut is not None:
            gyr[cut:], acc[cut:] = rng.normal(0.0, 3.0, gyr[cut:].shape), rng.normal(0.0, 20.0, acc[cut:].shape)
        out[n] = dataclasses.replace(s, gyr=gyr, acc=acc, mag=s.mag.copy())
    return dataclasses.replace(bs, sensors=out)


@pytest.fixture(scope="module")
def turned():
    from imugraph.sim.body import simulate_body

    skel, mo, place, prm, rng = _sim(BVH, duration_s=28.0, turn=True)
    return _garbage_after(simulate_body(mo, skel, place, prm, rng, name="turned"), None)


def _lag_start(bs, causal: bool):
    """(filtered n_quat, cut row) of the fixed lag 1 s with (L7), and of the same session with garbage from cut on."""
    from imugraph.graphs.body_incremental import solve_body_incremental
    from imugraph.graphs.body_model import BodyOptions

    opts = BodyOptions(lag_bootstrap_marginal=True, lag_init_causal=causal)
    res = solve_body_incremental(bs, opts, lag_s=1.0)
    chunk = 5 * opts.keyframe_every                  # update_every × keyframe_every: one update's rows at most
    cut = int(np.searchsorted(bs.t, bs.t[0] + res.info["bootstrap"]["bootstrap_s"])) + opts.keyframe_every + 2 * chunk
    assert cut < bs.n - 60                           # the garbage covers most of the motion window of init "auto"
    res_g = solve_body_incremental(_garbage_after(bs, cut), opts, lag_s=1.0)
    return res.info["filtered"].n_quat[: cut - chunk], res_g.info["filtered"].n_quat[: cut - chunk], res


def test_lag_start_does_not_read_rows_after_its_bootstrap(turned):
    a, b, res = _lag_start(turned, causal=True)
    assert res.info["init_motion"]["_switched"]      # the motion start is in play (sensors turned 0–360°)
    assert np.array_equal(a, b)                      # the first output bit for bit, whatever comes later


def test_without_the_option_the_lag_start_reads_later_rows(turned):
    a, b, _ = _lag_start(turned, causal=False)      # today's (L7) start: the k = 0 priors from 30 s of motion
    d = np.abs(np.sum(a * b, axis=-1))
    assert np.degrees(2 * np.arccos(np.clip(d, 0, 1))).max() > 1.0


@pytest.fixture(scope="module")
def mid_rest(tmp_path_factory):
    """CMU 131_01 (5 s, moving throughout) run backwards into its N-pose, then forwards: [motion reversed | N-pose
    N-pose | motion]; its only common rest is the 4 s N-pose in the middle, around `half` (8 s)."""
    from imugraph.io.body_session import write_body_session
    from imugraph.sim.body import simulate_body

    skel, mo, place, prm, rng = _sim(CMU, duration_s=5.0, seed=1)
    n = mo.t.size
    mo2 = dataclasses.replace(mo, t=np.arange(2 * n - 1) * float(np.median(np.diff(mo.t))),
                              n_quat=np.concatenate([mo.n_quat[::-1], mo.n_quat[1:]]),
                              n_pos=np.concatenate([mo.n_pos[::-1], mo.n_pos[1:]]))
    bs = simulate_body(mo2, skel, place, prm, rng, name="mid_rest")
    folder = tmp_path_factory.mktemp("b23") / "mid_rest"
    write_body_session(folder, bs)
    return bs, folder, float(mo.t[-1] - mo.t[0])


def test_rest_in_the_middle_is_found(mid_rest):
    from imugraph.graphs.body_init import find_npose
    from imugraph.graphs.body_model import BodyOptions, npose_samples

    bs, _, half = mid_rest
    assert npose_samples(bs, BodyOptions())[1] == "assumed"          # today: the moving first samples
    idx, method, info = find_npose(bs, BodyOptions())
    assert method == "found"
    t0, t1 = info["t0"] - bs.t[0], info["t1"] - bs.t[0]
    assert half - 2.6 <= t0 and t1 <= half + 2.6 and t1 - t0 >= 3.0, (t0, t1, half)   # N-pose ±2 s (+ the blend's ends)


def test_mocap_solves_from_the_rest_found(mid_rest, tmp_path, capsys):
    from imugraph import cli

    bs, folder, half = mid_rest
    out = tmp_path / "out"
    assert cli.main(["mocap", str(folder), "--out", str(out), "--quiet", "--npose-search", "anywhere"]) == 0
    err = capsys.readouterr().err
    assert "quietest common rest" in err and "mid_rest" in err
    info = json.loads((out / "mocap_info.json").read_text())
    assert info["npose_search"]["method"] == "found"
    assert info["scores"]["joint_rmse_max_deg"] < 5.0                 # vs the simulator's truth, from the rest on
    t = np.load(out / "mocap.npz")["t"]
    assert abs(t[0] - info["npose_search"]["t0"]) < 1e-9


def test_session_without_rest_refuses_in_one_line(tmp_path, capsys):
    from imugraph import cli
    from imugraph.io.body_session import write_body_session
    from imugraph.sim.body import simulate_body

    skel, mo, place, prm, rng = _sim(CMU, seed=0)
    bs = simulate_body(mo, skel, place, prm, rng, name="moving")
    bs = bs.slice(int(np.searchsorted(bs.t, bs.t[0] + 5.0)), bs.n)    # N-pose and blend cut off: moving throughout
    folder = tmp_path / "moving"
    write_body_session(folder, bs)
    out = tmp_path / "out"
    assert cli.main(["mocap", str(folder), "--out", str(out), "--quiet", "--npose-search", "anywhere"]) == 2
    lines = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("imugraph: error:")
    assert "moving" in lines[0] and "--npose T0,T1" in lines[0] and "no common rest" in lines[0]
    assert not out.exists()                                           # no empty output folder


def test_rest_at_the_start_is_left_as_today(mid_rest):
    from imugraph.graphs.body_init import find_npose
    from imugraph.graphs.body_model import BodyOptions, npose_samples

    bs, _, half = mid_rest
    start = bs.slice(int(np.searchsorted(bs.t, bs.t[0] + half - 1.0)), bs.n)     # begins inside the N-pose
    idx, method = npose_samples(start, BodyOptions())
    idx2, method2, info = find_npose(start, BodyOptions())
    assert method == method2 == "detected" and np.array_equal(idx, idx2) and info["start_row"] == 0
