"""The stream's bootstrap guard (a gyro bias that contradicts the initial rest is refused) and the iSAM2
factorization option."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.errors import SessionError
from imugraph.evaluate import orientation_error
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_run import BIAS_TOL, bootstrap_calibration, rest_gyro_bias, stream_session
from imugraph.sim.scenario import distorted_session


@pytest.fixture(scope="module")
def sim():
    return distorted_session(5, 40.0, 100.0)


def test_rest_gyro_bias_is_the_true_bias(sim):
    """distorted_session rests for its first 2 s: the mean gyro there is the true bias within the noise
    (σ 0.01 rad/s per sample, ≈ 200 samples: SEM 0.0007); a window starting in motion gives None."""
    session, truth = sim
    b = rest_gyro_bias(session)
    assert b is not None and np.max(np.abs(b - truth.gyro_bias)) < 0.003
    moving = session.slice(int(10 * session.rate), session.n)
    assert rest_gyro_bias(moving) is None


def test_bootstrap_refuses_a_bias_that_contradicts_the_rest(sim, monkeypatch):
    """A bootstrap whose gyro bias is BIAS_TOL off the rest's is not used: the window grows until one agrees
    (here: calibrate is replaced by a stub that is wrong on windows shorter than 25 s)."""
    session, truth = sim
    from imugraph.calibration import ml

    good = truth.to_calibration()
    seen = []

    class Est:
        def __init__(self, cal):
            self.calibration = cal

    def fake(sub, options=None, allow_weak=False):
        seen.append(sub.n)
        dur = sub.t[-1] - sub.t[0]
        return Est(good if dur >= 25.0 else replace(good, gyro_bias=good.gyro_bias + 3 * BIAS_TOL))

    monkeypatch.setattr(ml, "calibrate", fake)
    cal, n = bootstrap_calibration(session, 10.0)
    assert len(seen) == 4 and n == seen[-1]            # 10 → 15 → 22.5 → 33.75 s
    assert np.allclose(cal.gyro_bias, good.gyro_bias)


def test_factorization_option(sim):
    """QR (default) and Cholesky solve the same system: same filtered output on a well-posed simulation; an
    unknown name is a SessionError."""
    session, truth = sim
    cal = truth.to_calibration()
    part = session.slice(0, 1500)
    out = {}
    for f in ("QR", "CHOLESKY"):
        r = stream_session(part, cal, StreamOptions(lag_s=2.0, fixed_lag_solver="incremental", factorization=f,
                                                    online_calibration=False))
        assert r.counts["failed_updates"] == 0
        out[f] = r.filtered
    gap = orientation_error(out["QR"], out["CHOLESKY"], None, part.rate, heading=False, max_shift=0.0).rms_deg
    assert gap < 1e-3
    with pytest.raises(SessionError):
        StreamSmoother(cal, 100.0, StreamOptions(factorization="LU"))
