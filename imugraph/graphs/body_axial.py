"""Soft axial sensor-to-segment rotations in the body graph (option `BodyOptions.axial_segments`).

For each segment in `axial_segments` the sensor may turn about the segment's long axis over time (model and
equations in imugraph.factors.body_axial, (S1)–(S4)): per keyframe a Vector1 φ with the Gauss–Markov prior
(S2), per segment one constant offset c (weak prior `axial_offset_sigma_rad`), and the hinges (B4) of joints
touching such a segment become the hinge (S3) with θ = c + φ. Like the fixed hinges, these factors need the
N-pose sensor-to-segment rotations and are emitted in the second pass (`pb.bRs_fixed` set), which is also why
only hinges make θ observable: no other factor sees the segment orientation (the joints (B2) are blind to a
turn about the line through both joint centres).

Output: nRb(t) = nRs(t) bRsᵀ Exp(−θ(t) â) with θ linearly interpolated between keyframes (`axial_angles`;
`BodyResult.info["axial_theta"]`). Batch only: the incremental solvers emit no hinges, so no θ either.

Measured (issue 4b; not a default — the option is off):
- synthetic chain, hinge knee, shank sensor turning ±8° about the shank (tests/test_body_axial.py): knee RMS
  error 4.68° rigid, 4.65° with the hinge, 1.07° with `axial_segments=("RightLowerLeg",)` (θ follows the
  injected turn, correlation 0.995); no artefact: 0.31° → 0.44°.
- real walk, `benchmarks/gaittoolbox_walk.py --hinges knees --axial A` (offset / held-out handling; defaults:
  L hip 6.04 / 6.48, R hip 3.15 / 3.24, mean 5.01 / 4.98; MVN L hip 5.83 / 6.27):
  A = thighs (the knee sets the thigh's axial rotation): L hip 7.61 / 6.04, R hip 6.15 / 5.01, mean 5.76 / 4.91;
  A = shanks: L hip 6.05 / 6.45, R hip 3.23 / 3.23, knees 3.16, 4.19 / 3.24, 5.33, ankles 4.50, 5.97 / 4.60,
  5.70, mean 4.51 / 4.76; A = legs: L hip 6.96 / 6.50, R hip 5.40 / 4.32, mean 5.12 / 4.69. The knee-implied
  turn of the thigh is uncorrelated with the thigh's axial error against Vicon (−0.15 both sides) and its gain
  on the knee flexion has the opposite sign (benchmarks/body_walk_diagnosis.py, section 7): the thigh error is
  not what a hinge knee can see.
- simulation (issue 4a, `benchmarks/body_sim_accuracy.py --mag off --hinges knees --axial shanks`): CMU 131_01
  1.47°, 131_02 0.92°, Xsens walk 7.42° (LeftKnee; with `--hinges knees` alone 4.16°, RightKnee): that motion
  is MVN's own estimate, whose knees turn 7.5° RMS internally/externally (range 45°), not a hinge.
"""

from __future__ import annotations

import gtsam
import numpy as np

from imugraph.errors import SessionError
from imugraph.factors import body as bf
from imugraph.factors import body_axial as ba
from imugraph.graphs.body_model import axial_sigma


def active(pb) -> bool:
    """True when the problem carries the soft axial rotations (option set and the second pass running)."""
    return bool(pb.opts.axial_segments) and pb.bRs_fixed is not None


def axial_joint(pb, jt) -> bool:
    """True when hinge joint `jt` touches a segment with a soft axial rotation (then (S3) replaces (B4))."""
    return active(pb) and jt.child in pb.opts.hinges and (jt.parent in pb.opts.axial_segments
                                                          or jt.child in pb.opts.axial_segments)


def sensor_index(pb, name: str) -> int:
    """Index of the sensed segment `name` of `axial_segments` (SessionError when it carries no sensor)."""
    if name not in pb.names:
        raise SessionError(pb.session.source, "axial_segments", repr(name), f"sensed segments {pb.names}")
    return pb.names.index(name)


def _theta_keys(pb, name: str, k: int) -> tuple:
    if name not in pb.opts.axial_segments:
        return ()
    s = sensor_index(pb, name)
    return (ba.axial_key(s, k), ba.axial_offset_key(s))


def axial_factors_at(pb, k: int) -> gtsam.NonlinearFactorGraph:
    """Factors of keyframe k: the priors (S2) (and the offset priors at k = 0) and the hinges (S3)."""
    g = gtsam.NonlinearFactorGraph()
    if not active(pb):
        return g
    o = pb.opts
    for name in o.axial_segments:
        s = sensor_index(pb, name)
        if k == 0:
            g.add(ba.scalar_prior(ba.axial_key(s, 0), axial_sigma(o, name)))
            g.add(ba.scalar_prior(ba.axial_offset_key(s), o.axial_offset_sigma_rad))
        else:
            g.add(ba.gauss_markov_link(ba.axial_key(s, k - 1), ba.axial_key(s, k), pb.kf_t[k] - pb.kf_t[k - 1],
                                       axial_sigma(o, name), o.axial_tau_s))
    model = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(o.axial_hinge_sigmas_rad, float))
    for jt in pb.joints:
        if not axial_joint(pb, jt):
            continue
        P, C = pb.names.index(jt.parent), pb.names.index(jt.child)
        g.add(ba.axial_hinge_factor(model, bf.pose_key(P, k), bf.pose_key(C, k), pb.bRs_fixed[jt.parent],
                                    pb.bRs_fixed[jt.child], ba.long_axis(pb.skel, jt.parent),
                                    ba.long_axis(pb.skel, jt.child), _theta_keys(pb, jt.parent, k),
                                    _theta_keys(pb, jt.child, k)))
    return g


def insert_initial(pb, values: gtsam.Values) -> gtsam.Values:
    """A copy of `values` with θ = 0 (φ_k = 0, c = 0) inserted where missing."""
    out = gtsam.Values(values)
    if not active(pb):
        return out
    for name in pb.opts.axial_segments:
        s = sensor_index(pb, name)
        for key in [ba.axial_key(s, k) for k in range(pb.K)] + [ba.axial_offset_key(s)]:
            if not out.exists(key):
                out.insert(key, np.zeros(1))
    return out


def axial_angles(pb, x: gtsam.Values, name: str) -> np.ndarray | None:
    """(N,) θ(t) = c + φ(t) of segment `name` at every input sample (linear between keyframes), rad; None when
    the solution has no soft axial rotation for it."""
    if name not in pb.opts.axial_segments or not active(pb):
        return None
    s = sensor_index(pb, name)
    if not x.exists(ba.axial_offset_key(s)):
        return None
    phi = np.array([x.atVector(ba.axial_key(s, k))[0] for k in range(pb.K)])
    c = float(x.atVector(ba.axial_offset_key(s))[0])
    return c + np.interp(np.arange(np.asarray(pb.session.t).size), pb.kf, phi)
