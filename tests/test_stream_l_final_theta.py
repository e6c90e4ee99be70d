"""StreamOptions.calib_final_theta (session 17, helper L): the end-of-stream graph's magnetometer factors at the
streamed θ instead of the pin θ₀ — the smoothed output with the calibration the stream estimated, as the batch
smooths with the θ it estimated; the filtered output unchanged."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.evaluate import orientation_error
from imugraph.factors.theta import unpack_theta
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.sim.scenario import distorted_session


def _stream(session, cal, **opt):
    sm = StreamSmoother(cal, session.rate, StreamOptions(**{"lag_s": None, **opt}),
                        g0=float(np.median(np.linalg.norm(session.acc, axis=1))))
    q = np.array([sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i]) for i in range(session.n)])
    sm.finish()
    return sm, q


@pytest.fixture(scope="module")
def runs():
    """Simulation, a start calibration 3 % of the field scale off in every entry of D and o; full iSAM2 with θ as a
    pinned graph state (the defaults), the end graph at θ₀ (off) and at the streamed θ (on, the default)."""
    session, truth = distorted_session(3, 60.0, 50.0)
    cal = truth.to_calibration()
    scale = np.cbrt(abs(np.linalg.det(cal.D)))
    rng = np.random.default_rng(0)
    start = replace(cal, D=cal.D + 0.03 * scale * rng.standard_normal((3, 3)),
                    o=cal.o + 0.03 * scale * rng.standard_normal(3))
    off, q_off = _stream(session, start, calib_final_theta=False)
    on, q_on = _stream(session, start)             # the default since session 17
    assert StreamOptions().calib_final_theta
    return session, cal, start, (off, q_off), (on, q_on)


def _truth_rms(q, session):
    return orientation_error(q, session.quat, None, session.rate, heading=False, max_shift=0.0).rms_deg


def test_filtered_output_unchanged(runs):
    """Only the end graph changes: the filtered orientations are identical sample by sample."""
    _, _, _, (_, q_off), (_, q_on) = runs
    assert np.array_equal(q_off, q_on)


def test_end_graph_uses_the_streamed_theta(runs):
    """The streamed θ the end graph used is closer to the true calibration than the start (the stream learned it)
    and the smoothed output with it is closer to the simulated truth than the one at the pin θ₀."""
    session, cal, start, (off, _), (on, _) = runs
    D, o, _ = unpack_theta(on._theta_end)
    err = lambda D_, o_: np.abs(np.r_[(D_ - cal.D).ravel(), o_ - cal.o]).max()
    assert err(D, o) < 0.5 * err(start.D, start.o)
    e_off, e_on = _truth_rms(off.smoothed(), session), _truth_rms(on.smoothed(), session)
    assert e_on < e_off, (e_on, e_off)
