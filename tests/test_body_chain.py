"""Unsensed links as estimated segments (imugraph.graphs.body_chain, BodyOptions.unsensed_sigma_rad)."""

import sys
from pathlib import Path
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from imugraph.factors import body as bf
from imugraph.geometry import expmap
from imugraph.graphs import body_chain as bc
from imugraph.graphs.body import solve_body_batch
from imugraph.graphs.body_model import BodyOptions, body_joints

sys.path.insert(0, str(Path(__file__).resolve().parent))
from body_synth import chain_session, chain_skeleton  # noqa: E402


def _rand_rot(rng, deg=60.0):
    a = rng.standard_normal(3)
    return expmap(a / np.linalg.norm(a) * np.deg2rad(rng.uniform(5.0, deg)))


def test_shared_prior_puts_links_on_the_geodesic_at_the_tie_fractions():
    """(C4) alone: with both sensed neighbours held, 3 links land at 1/4, 1/2, 3/4 of the geodesic (K2),
    expected values from scipy's Slerp of the segment orientations nRs bRsᵀ."""
    rng = np.random.default_rng(4)
    RsA, RsD, bRsA, bRsD = (_rand_rot(rng) for _ in range(4))
    A, D, U = bf.pose_key(0, 0), bf.pose_key(1, 0), [bc.link_pose_key(i, 0) for i in range(3)]
    g = gtsam.NonlinearFactorGraph()
    tight = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    g.add(gtsam.PriorFactorPose3(A, gtsam.Pose3(gtsam.Rot3(RsA), np.zeros(3)), tight))
    g.add(gtsam.PriorFactorPose3(D, gtsam.Pose3(gtsam.Rot3(RsD), np.ones(3)), tight))
    free_rot = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, 1e6), np.full(3, 1.0)])
    for u in U:                                   # translation gauge only
        g.add(gtsam.PriorFactorPose3(u, gtsam.Pose3(), free_rot))
    chain = [A] + U + [D]
    meas = [bRsA.T, np.eye(3), np.eye(3), bRsD]
    for a, b, m in zip(chain[:-1], chain[1:], meas):
        g.add(bc._rot_prior(a, b, m, 0.3))
    x0 = gtsam.Values()
    x0.insert(A, gtsam.Pose3(gtsam.Rot3(RsA), np.zeros(3)))
    x0.insert(D, gtsam.Pose3(gtsam.Rot3(RsD), np.ones(3)))
    for u in U:
        x0.insert(u, gtsam.Pose3())
    prm = gtsam.LevenbergMarquardtParams()
    prm.setRelativeErrorTol(1e-14)
    prm.setAbsoluteErrorTol(1e-14)
    prm.setMaxIterations(200)
    x = gtsam.LevenbergMarquardtOptimizer(g, x0, prm).optimize()
    seg = Rotation.from_matrix(np.stack([RsA @ bRsA.T, RsD @ bRsD.T]))
    want = Slerp([0.0, 1.0], seg)([0.25, 0.5, 0.75]).as_matrix()
    for u, W in zip(U, want):
        err = Rotation.from_matrix(W.T @ x.atPose3(u).rotation().matrix()).magnitude()
        assert np.rad2deg(err) < 1e-3


def _fake_problem(prior: str, K: int = 3, seed: int = 0, npose_sigma=None, gain=None):
    skel = chain_skeleton(with_spine=True)
    rng = np.random.default_rng(seed)
    names = sorted(skel.sensed, key=skel.index)
    opts = BodyOptions(unsensed_sigma_rad=0.4, unsensed_prior=prior, unsensed_npose_sigma_rad=npose_sigma,
                       unsensed_sigma_gain=gain)
    pb = SimpleNamespace(skel=skel, opts=opts, names=names, joints=body_joints(skel), K=K, kf=np.arange(K) * 6,
                         npose_idx=np.arange(4))
    place = {n: (_rand_rot(rng, 30.0), rng.normal(0.0, 0.05, 3)) for n in names}
    pb.chains = bc.make_chains(pb, place)
    x = gtsam.Values()
    for s, n in enumerate(names):
        for k in range(K):
            x.insert(bf.pose_key(s, k), gtsam.Pose3(gtsam.Rot3(_rand_rot(rng, 90.0)), rng.normal(0, 0.3, 3)))
    pb.chain_targets = bc.tie_targets(pb, x, place)
    pb.chain_angles = bc.tie_angles(pb, x, place)
    for j, jt in enumerate(pb.joints):
        for k in range(K):
            x.insert(bf.joint_key(j, k), rng.normal(0.0, 0.3, 3))
    return pb, place, bc.insert_initial(pb, x, place)


@pytest.mark.parametrize("prior, npose_sigma, gain", [("shared", None, None), ("fixed", None, None),
                                                      ("fixed", 0.05, None), ("fixed", None, 2.0)])
def test_chain_factors_gradient_matches_numerical_derivative(prior, npose_sigma, gain):
    """(C1)–(C4) linearised by gtsam agree with central differences of the graph's cost along every tangent
    direction of every variable (a random configuration, residuals far from zero)."""
    pb, place, x = _fake_problem(prior, npose_sigma=npose_sigma, gain=gain)
    rng = np.random.default_rng(1)
    step = gtsam.VectorValues()
    for key in x.keys():
        step.insert(key, rng.normal(0.0, 0.05, bf.key_dim(key)))
    x = x.retract(step)
    g = gtsam.NonlinearFactorGraph()
    for k in range(pb.K):
        g.push_back(bc.chain_factors_at(pb, k, place))
    assert g.size() > 0
    grad = g.linearize(x).gradientAtZero()
    h = 1e-6
    for key in x.keys():
        if not any(key in g.at(i).keys() for i in range(g.size())):
            continue
        d = bf.key_dim(key)
        for i in range(d):
            e = np.zeros(d)
            e[i] = h
            vp, vm = gtsam.VectorValues(), gtsam.VectorValues()
            vp.insert(key, e)
            vm.insert(key, -e)
            num = (g.error(x.retract(vp)) - g.error(x.retract(vm))) / (2 * h)
            ana = grad.at(key)[i]
            assert abs(num - ana) <= 1e-4 * max(1.0, abs(num)), (gtsam.DefaultKeyFormatter(key), i, num, ana)


def test_chain_factors_vanish_on_a_consistent_configuration():
    """(C1)–(C3) are zero where the link sits at its joints and (C4') where it equals its target."""
    pb, place, x = _fake_problem("fixed", K=1)
    g = bc.chain_factors_at(pb, 0, place)
    priors = [i for i in range(g.size()) if isinstance(g.at(i), gtsam.PriorFactorPoint3)]
    assert priors
    # insert_initial puts the links on the targets, the joints by forward kinematics from A: only the
    # lumped joint centre J (D's origin) and D's side are not yet consistent
    c = pb.chains[0]
    U = x.atPose3(bc.link_pose_key(c.first, 0))
    J = U.transformFrom(np.asarray(c.lever_nom[-1], float))
    x.update(bf.joint_key(c.joint, 0), J)
    for i in range(g.size()):
        f = g.at(i)
        if isinstance(f, gtsam.PriorFactorPose3):      # rotation on target; translation σ 1 km: (0.3 m/1 km)²
            assert f.error(x) < 1e-6
        elif not isinstance(f, gtsam.PriorFactorPoint3):
            assert f.error(x) < 1e-12, type(f).__name__


def test_tie_angles_are_the_bend_between_the_sensed_ends():
    """θ_k of (C6) equals the angle of nR_Aᵀ nR_D with nR = nRs bRsᵀ (scipy's magnitude, independent)."""
    pb, place, x = _fake_problem("fixed", gain=1.0)
    c = pb.chains[0]
    th = bc.tie_angles(pb, x, place)[c.first]
    for k in range(pb.K):
        RA = x.atPose3(bf.pose_key(pb.names.index(c.parent), k)).rotation().matrix() @ place[c.parent][0].T
        RD = x.atPose3(bf.pose_key(pb.names.index(c.child), k)).rotation().matrix() @ place[c.child][0].T
        assert th[k] == pytest.approx(Rotation.from_matrix(RA.T @ RD).magnitude(), abs=1e-9)


def test_unsensed_l5_option_runs_and_keeps_the_sensed_pairs():
    """Batch with the spine's L5 estimated (both priors): the sensed pair Pelvis → T8 and the knee stay
    as accurate as with the lumped joint, and the output carries L5 from the graph."""
    from test_body_graph import joint_errors, pair_error
    sess = chain_session(duration_s=8.0, seed=3, with_spine=True)
    base = solve_body_batch(sess, BodyOptions())
    for kw in ({"unsensed_prior": "shared"}, {"unsensed_prior": "fixed", "unsensed_sigma_gain": 10.0}):
        res = solve_body_batch(sess, BodyOptions(unsensed_sigma_rad=0.3, **kw))
        assert len(res.info["passes"]) == 2
        assert pair_error(sess, res, "Pelvis", "T8") < max(1.5, pair_error(sess, base, "Pelvis", "T8") + 0.3)
        assert joint_errors(sess, res)["RightLowerLeg"] < 1.5
