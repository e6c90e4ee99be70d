"""The fixed lag's own neck bend and bootstrap (helper L22): imugraph.graphs.body_lag_neck (L1)–(L4) and
imugraph.graphs.body_lag_boot (L5) lag_bootstrap_overlap_s, (L7) lag_bootstrap_marginal.

The bent-link session of tests/test_body_neck.py (L5 held at a constant 20° bend relative to the pelvis, blended in
between 2 and 3 s, T8 turning freely on it; unsensed_bend=("T8",)) with the AUTO bootstrap, which ends at 3.7 s —
before the bend can be seen, so helper L21's bend read once in the bootstrap misses it (test_body_neck: 11°)."""

import sys
from pathlib import Path

import numpy as np
import pytest

from imugraph.graphs.body_incremental import solve_body_incremental
from imugraph.graphs.body_lag_boot import overlap_start
from imugraph.graphs.body_model import BodyOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_body_neck import _bent_link_session, _link_error_deg  # noqa: E402

KW = dict(unsensed_bend=("T8",), lever_prior_frame="lumped", lever_pass_iterations=None)


@pytest.fixture
def bent_link_session(monkeypatch):
    return _bent_link_session(monkeypatch, mag=False)


def test_stream_estimates_the_bend_the_short_bootstrap_missed(bent_link_session):
    """lag_neck_stream: the bend (N5) read from the stream's own levers as the motion goes on beats both the ties and
    the bend of the (too short) bootstrap; each output keyframe carries the bend known when it left the window.
    Measured when written (link error, deg): ties 14.2, L21's bootstrap bend 11.1, stream anchored 9.8, stream with
    the bootstrap's factors in the smoother (L7) 5.1 (filtered 6.0); the keyframes before the auto bootstrap's end
    (3.7 s) keep the bootstrap's bend — the causal price."""
    sess = bent_link_session
    ties = solve_body_incremental(sess, BodyOptions(**KW), lag_s=1.0)
    boot = solve_body_incremental(sess, BodyOptions(lag_neck_from_bootstrap=True, **KW), lag_s=1.0)
    on = solve_body_incremental(sess, BodyOptions(lag_neck_stream=True, **KW), lag_s=1.0)
    marg = solve_body_incremental(sess, BodyOptions(lag_neck_stream=True, lag_bootstrap_marginal=True, **KW), lag_s=1.0)
    assert on.info["bootstrap"]["bootstrap_s"] < 4.0            # the auto bootstrap: before the bend is visible
    e_ties, e_boot, e_on, e_marg = (_link_error_deg(sess, r) for r in (ties, boot, on, marg))
    assert e_on < min(e_ties, e_boot) - 1.0
    assert e_marg < 0.6 * min(e_ties, e_boot)
    bends = [r["bend"]["L5"][1] for r in marg.info["lag_records"]]
    assert not np.allclose(bends[0], bends[-1])                 # the bend moves with the stream's levers
    assert _link_error_deg(sess, marg.info["filtered"]) < 0.6 * min(e_ties, e_boot)   # filtered: right after update


def test_stream_neck_off_keeps_the_ties(bent_link_session):
    """Without the option the records carry no bend and the link keeps the ties (the default path untouched)."""
    res = solve_body_incremental(bent_link_session, BodyOptions(**KW), lag_s=1.0)
    assert all("bend" not in r for r in res.info["lag_records"])


def test_marginal_bootstrap_keeps_improving_the_placements(bent_link_session):
    """lag_bootstrap_marginal (L7): the bootstrap's factors go into the smoother, the N-pose keyframes stay in the
    window, so the placements bRs the output uses change after the bootstrap (anchored: held), end closer to the
    truth's, and every update succeeds."""
    sess = bent_link_session
    anch = solve_body_incremental(sess, BodyOptions(**KW), lag_s=1.0)
    marg = solve_body_incremental(sess, BodyOptions(lag_bootstrap_marginal=True, **KW), lag_s=1.0)
    assert marg.info["failed_updates"] == 0
    name = next(iter(marg.placements))

    def bRs(res, k):
        return res.info["lag_records"][k]["place"][name][0]

    K = len(marg.info["lag_records"])
    assert K == len(anch.info["lag_records"])
    assert np.allclose(bRs(anch, K // 2), bRs(anch, K - 1))    # anchored: the bootstrap's, held
    assert not np.allclose(bRs(marg, K // 2), bRs(marg, K - 1), atol=1e-6)
    truth = {n: np.asarray(p["bRs"]) for n, p in sess.truth["placements"].items()}
    err = {lab: max(np.rad2deg(np.arccos(np.clip((np.trace(truth[n].T @ r.placements[n]["bRs"]) - 1) / 2, -1, 1)))
                    for n in r.placements) for lab, r in (("anch", anch), ("marg", marg))}
    assert err["marg"] < err["anch"] - 1.0     # the worst sensor's bRs after the stream beats the bootstrap's
                                               # (measured when written: 6.5° vs 9.4°)


class _PB:
    """The fields overlap_start reads: keyframe sample indices and times, the N-pose's last sample."""
    def __init__(self):
        self.kf = np.arange(0, 100, 10)                          # keyframes at samples 0, 10, …, 90
        self.kf_t = self.kf / 10.0                               # … at 0, 1, …, 9 s
        self.npose_idx = np.array([0, 25])                       # the N-pose ends at sample 25 (keyframes 0–2)


def testoverlap_start_restreams_the_last_seconds_but_never_the_npose():
    pb = _PB()
    assert overlap_start(pb, 8, 0.0) == 8                       # off: the stream starts after the bootstrap
    assert overlap_start(pb, 8, 2.5) == 5                       # keyframes at 5, 6, 7 s (7 − t < 2.5)
    assert overlap_start(pb, 8, 100.0) == 3                     # never into the N-pose (keyframes 0–2)
