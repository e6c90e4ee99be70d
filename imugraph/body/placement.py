"""Nominal pose of an IMU on its body segment (the sensor-to-segment prior of the estimator and the
simulator's starting point for random placements).

A sensor sits on the skin at a site of its segment (`SITES`: a fraction along the segment's end vector,
the outward surface normal there, the soft-tissue depth from the bone axis), with

    z_s = outward normal n̂,   x_s = the segment's long axis projected on the skin plane,
    y_s = z_s × x_s,   bRs = [x_s y_s z_s],   b_pos = frac · b_end + depth · n̂                      (N1)

(the strap-on layout of e.g. Xsens MVN suits: sensor flat on the skin, cable/long side along the limb).
Frames as in imugraph.body.skeleton: x anterior, y left, z up in the neutral pose; "lateral" is −y on the
right side and +y on the left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Sensor sites: segment-name suffix → (fraction along the segment's end vector, outward normal in b, skin depth m)
SITES = {"Pelvis": (0.5, (-1, 0, 0), 0.10), "T8": (0.5, (1, 0, 0), 0.10), "Head": (0.7, (1, 0, 0), 0.09),
         "Shoulder": (0.5, (-1, 0, 0), 0.06), "UpperArm": (0.5, "lateral", 0.045),
         "ForeArm": (0.7, "lateral", 0.035), "Hand": (0.5, "lateral", 0.015),
         "UpperLeg": (0.5, "lateral", 0.07), "LowerLeg": (0.4, (1, 0, 0), 0.05), "Foot": (0.5, (0, 0, 1), 0.03)}
DEFAULT_SITE = (0.5, (1, 0, 0), 0.05)        # segments without a listed suffix: front, mid-segment


@dataclass(frozen=True)
class Placement:
    """Pose of a sensor on its segment: bRs (3, 3) sensor → segment; b_pos (3,) sensor origin in b, m."""

    bRs: np.ndarray
    b_pos: np.ndarray

    def to_dict(self) -> dict:
        return {"bRs": np.asarray(self.bRs, float), "b_pos": np.asarray(self.b_pos, float)}


def nominal_placement(skel, name: str) -> Placement:
    """Sensor on the skin of segment `name` (eq. N1); `skel` needs `index(name)` and `ends`."""
    i = skel.index(name)
    key = next((k for k in SITES if name.endswith(k)), None)
    frac, normal, depth = SITES.get(key, DEFAULT_SITE)
    if normal == "lateral":
        normal = (0, -1, 0) if name.startswith("Right") else (0, 1, 0)
    z = np.asarray(normal, float)
    axis = np.asarray(skel.ends[i], float)
    x = axis - np.dot(axis, z) * z                                   # long axis in the skin plane
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 0.0, 1.0]) - z[2] * z
    if np.linalg.norm(x) < 1e-6:                                     # normal along z (foot) and no length
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    bRs = np.column_stack([x, np.cross(z, x), z])                    # (N1)
    return Placement(bRs=bRs, b_pos=frac * axis + depth * z)


def nominal_placements(skel, names=None) -> dict:
    """{segment: (bRs, b_pos)} of `nominal_placement` for `names` (default: the sensed segments), in the
    form of `imugraph.graphs.body_model.BodyOptions.placements`."""
    out = {}
    for n in (skel.sensed if names is None else names):
        p = nominal_placement(skel, n)
        out[n] = (p.bRs, p.b_pos)
    return out
