"""Skeleton from an option string (imugraph.body.skeleton.skeleton_from_spec) and the gaittoolbox reader's
`skeleton=` keyword: a skeleton read from a BVH has the BVH's lengths; bad input names the file."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.body.skeleton import LOWER_BODY, lower_body, skeleton_from_spec
from imugraph.config import data_dir
from imugraph.errors import SessionError

# A lower body in centimetres, Xsens MVN joint names (y up, z forward, x to the subject's left). The
# expected values below are these OFFSETs read by hand: hips ±9 cm lateral, thigh 45 cm, shank 40 cm.
_LEG = """ JOINT {s}Hip
 {{
  OFFSET {x} 0.0 0.0
  CHANNELS 3 Zrotation Xrotation Yrotation
  JOINT {s}Knee
  {{
   OFFSET 0.0 -45.0 0.0
   CHANNELS 3 Zrotation Xrotation Yrotation
   JOINT {s}Ankle
   {{
    OFFSET 0.0 -40.0 0.0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT {s}Toe
    {{
     OFFSET 0.0 -7.0 15.0
     CHANNELS 3 Zrotation Xrotation Yrotation
     End Site
     {{
      OFFSET 0.0 -1.0 6.0
     }}
    }}
   }}
  }}
 }}
"""
_CHEST = """ JOINT Chest
 {
  OFFSET 0.0 10.0 0.0
  CHANNELS 3 Zrotation Xrotation Yrotation
  End Site
  {
   OFFSET 0.0 50.0 0.0
  }
 }
"""


def _bvh(path, legs=True):
    body = (_LEG.format(s="Right", x=-9.0) + _LEG.format(s="Left", x=9.0)) if legs else _CHEST
    n = 6 + (24 if legs else 3)
    text = ("HIERARCHY\nROOT Hips\n{\n OFFSET 0.0 0.0 0.0\n"
            " CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n" + body + "}\n"
            "MOTION\nFrames: 2\nFrame Time: 0.01\n" + ("0.0 93.0 0.0" + " 0.0" * (n - 3) + "\n") * 2)
    path.write_text(text)
    return path


def test_bvh_skeleton_has_the_files_lengths(tmp_path):
    skel = skeleton_from_spec(f"bvh:{_bvh(tmp_path / 'legs.bvh')}")
    assert skel.names == LOWER_BODY
    off = dict(zip(skel.names, skel.offsets))
    np.testing.assert_allclose(off["LeftUpperLeg"], [0.0, 0.09, 0.0], atol=1e-9)      # x → left (n y)
    np.testing.assert_allclose(off["RightUpperLeg"], [0.0, -0.09, 0.0], atol=1e-9)
    for side in ("Left", "Right"):
        np.testing.assert_allclose(off[f"{side}LowerLeg"], [0.0, 0.0, -0.45], atol=1e-9)
        np.testing.assert_allclose(off[f"{side}Foot"], [0.0, 0.0, -0.40], atol=1e-9)
    # and not the nominal 1.75 m proportions (thigh 0.429 m, hips 0.334 m apart)
    assert not np.allclose(skel.offsets, lower_body(1.75).offsets, atol=0.01)


def test_height_and_nominal_specs():
    assert skeleton_from_spec(None) is None and skeleton_from_spec("nominal") is None
    skel = skeleton_from_spec("height:2.0")
    thigh = -dict(zip(skel.names, skel.offsets))["LeftLowerLeg"][2]
    assert thigh == pytest.approx((0.530 - 0.285) * 2.0)         # Winter: hip 0.530 H, knee 0.285 H


def test_bad_specs_name_the_file(tmp_path):
    missing = tmp_path / "nope.bvh"
    with pytest.raises(SessionError, match="nope.bvh"):
        skeleton_from_spec(f"bvh:{missing}")
    trunk = _bvh(tmp_path / "trunk.bvh", legs=False)
    with pytest.raises(SessionError, match=r"trunk\.bvh.*LeftUpperLeg|LeftUpperLeg.*trunk\.bvh"):
        skeleton_from_spec(f"bvh:{trunk}")
    for bad in ("bvh:", "height:tall", "cm:1.8", "height:9"):
        with pytest.raises(SessionError):
            skeleton_from_spec(bad)


@pytest.mark.skipif(not (data_dir() / "gaittoolbox" / "rawimu").is_dir(), reason="gaittoolbox data absent")
def test_gaittoolbox_reader_takes_the_mvn_hierarchy():
    from imugraph.io.gaittoolbox import read_gaittoolbox

    root = data_dir() / "gaittoolbox"
    s = read_gaittoolbox(root / "rawimu", skeleton=f"bvh:{root / 'xsens' / 'S02-Trial-Walk-1.bvh'}")
    off = dict(zip(s.skeleton.names, s.skeleton.offsets))
    # the file's OFFSETs (mm): LeftHip x 88.075452, LeftKnee y −484.915680, LeftAnkle y −392.968678
    assert off["LeftUpperLeg"][1] == pytest.approx(0.088075452, abs=1e-9)
    assert off["LeftLowerLeg"][2] == pytest.approx(-0.484915680, abs=1e-6)
    assert off["LeftFoot"][2] == pytest.approx(-0.392968678, abs=1e-6)
    assert "BVH hierarchy" in s.meta["skeleton"]
    with pytest.raises(SessionError, match="skeleton"):
        read_gaittoolbox(root / "rawimu", skeleton=lower_body().subset(("Pelvis", "LeftUpperLeg")))


def test_mocap_skeleton_option(tmp_path):
    import argparse

    from imugraph.commands.mocap import add_arguments, apply_skeleton
    from imugraph.io.body_session import BodySession

    p = argparse.ArgumentParser()
    add_arguments(p)
    assert p.parse_args(["x"]).skeleton == "nominal"
    spec = f"bvh:{_bvh(tmp_path / 'legs.bvh')}"
    assert p.parse_args(["x", "--skeleton", spec]).skeleton == spec
    base = lower_body()
    sensed = ("Pelvis", "LeftUpperLeg", "LeftLowerLeg")
    import dataclasses
    session = BodySession(t=np.arange(3) * 0.01, sensors={}, skeleton=dataclasses.replace(base, sensed=sensed))
    assert apply_skeleton(session, "nominal") is session
    out = apply_skeleton(session, spec)
    assert out.skeleton.sensed == sensed and out.skeleton.names == base.names
    assert dict(zip(out.skeleton.names, out.skeleton.offsets))["LeftLowerLeg"][2] == pytest.approx(-0.45)
    assert spec in out.meta["skeleton"]
    with pytest.raises(SessionError, match="trunk.bvh"):
        apply_skeleton(session, f"bvh:{_bvh(tmp_path / 'trunk.bvh', legs=False)}")
