"""U23 defects 2–3 (session 23, the lead): `imugraph mocap` says when it has to assume the N-pose (a session that
starts moving), and checks a given --npose window against the session."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imugraph import cli
from imugraph.io.body_session import write_body_session


BVH = "gaittoolbox/xsens/S02-Trial-Walk-1.bvh"


def _simulate(npose_s: float):
    """A 12 s simulation of the Xsens MVN walk (data directory; skipped without it), N-pose of npose_s s."""
    from imugraph.config import data_dir
    from imugraph.sim.body import motion_from_bvh, random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    if not (data_dir() / BVH).exists():
        pytest.skip(f"{BVH} absent")
    skel, mo = motion_from_bvh(data_dir() / BVH, rate_hz=60.0, npose_s=npose_s, blend_s=1.0, duration_s=12.0)
    rng = np.random.default_rng(1)
    place = random_placements(skel, rng, max_angle_deg=20.0, max_shift_m=0.02)
    prm = {n: SensorParams(gyro_bias=rng.normal(0.0, 0.01, 3), gyro_noise=np.full(3, 0.003),
                           acc_noise=np.full(3, 0.02), acc_bias=rng.normal(0.0, 0.05, 3)) for n in place}
    return simulate_body(mo, skel, place, prm, rng, name="walk")


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    bs = _simulate(2.0)
    d = tmp_path_factory.mktemp("walk") / "walk"
    write_body_session(d, bs)
    return d, bs


def test_given_npose_outside_session_refused(walk, tmp_path, capsys):
    d, bs = walk
    rc = cli.main(["mocap", str(d), "--out", str(tmp_path / "o"), "--quiet", "--npose", "0,1000"])
    err = capsys.readouterr().err
    assert rc == 2 and "--npose" in err and "1000" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_given_npose_recorded_and_moving_window_warned(walk, tmp_path, capsys):
    d, bs = walk
    t0 = float(bs.t[0])
    rc = cli.main(["mocap", str(d), "--out", str(tmp_path / "o"), "--quiet", "--npose", f"{t0 + 5},{t0 + 6}"])
    err = capsys.readouterr().err
    assert rc == 0 and "warning" in err and "standing rest" in err
    info = json.loads((tmp_path / "o" / "mocap_info.json").read_text())
    assert np.allclose(info["npose_window"], [t0 + 5, t0 + 6])


def test_assumed_npose_warned(walk, tmp_path, capsys):
    """The same walk with its N-pose cut off: solved as before, but the assumption is said (one warning line)."""
    d, bs = walk
    cut = bs.slice(int(4.0 * bs.rate), bs.n)
    d2 = tmp_path / "cut"
    write_body_session(d2, cut)
    rc = cli.main(["mocap", str(d2), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0 and "assumed to be the N-pose" in err and "--npose" in err
    rc = cli.main(["mocap", str(d), "--out", str(tmp_path / "o2"), "--quiet"])
    assert rc == 0 and "assumed" not in capsys.readouterr().err


def test_lag_bootstrap_note(walk, tmp_path, capsys):
    """U23 defect 10: `mocap --lag` on a session whose bootstrap takes (nearly) everything says so (console and
    timing.json)."""
    d, bs = walk
    short = bs.slice(0, int(3.0 * bs.rate))          # the 2 s N-pose and the 1 s blend: too little motion
    d2 = tmp_path / "short"
    write_body_session(d2, short)
    assert cli.main(["mocap", str(d2), "--out", str(tmp_path / "o"), "--quiet", "--lag", "1"]) == 0
    out = capsys.readouterr().out
    timing = json.loads((tmp_path / "o" / "timing.json").read_text())
    assert "batch solve, not a stream" in timing["bootstrap_note"] and "batch solve, not a stream" in out
    assert timing["bootstrap"]["span_s"] <= short.t[-1] - short.t[0] + 1e-9
