"""Task J2's options of the σ_p selection (calibration/position_select.py): the cross-field σ_d,y chosen after the
bound's ML rounds (position_select_field_rounds), the CPU options (position_select_stop, _max_iter: the candidates'
common preintegration computed once must give the same numbers), and "off" still returning the defaults exactly."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.calibration.ml import Options, calibrate


@pytest.fixture(scope="module")
def walk():
    from benchmarks.j2_travel import travel_session
    s, path = travel_session(1, "walk", duration_s=60.0)
    assert np.ptp(path[:, :2], axis=0).max() > 20.0
    return s


def test_off_with_the_j2_options_is_the_defaults_result(walk):
    opt = Options(position_select=(1e4, 1.0, 0.1), position_select_rounds=True, position_select_field=(0.006, 0.012),
                  position_select_field_rounds=True, position_select_max_iter=1)
    est = calibrate(walk, opt, allow_weak=True)
    assert est.info["position_sigma"] is None
    np.testing.assert_array_equal(est.quat, calibrate(walk, Options(), allow_weak=True).quat)


@pytest.mark.parametrize("cands", [(1e4,), (0.3,)])
def test_reused_preintegration_gives_the_same_result(walk, cands):
    """position_select_stop with one candidate never stops: it differs from the plain selection only by the
    preintegration computed once for the solves that share bias, noise and Ê (ml.py)."""
    plain = calibrate(walk, Options(position_select=cands, position_select_rounds=True), allow_weak=True)
    memo = calibrate(walk, Options(position_select=cands, position_select_rounds=True, position_select_stop=True),
                     allow_weak=True)
    np.testing.assert_array_equal(memo.quat, plain.quat)


def test_field_after_rounds_scores_its_candidates(walk):
    """A forced bound (one candidate): σ_d,y candidates are scored after the bound's rounds, the configured σ_y
    first; when it is kept, the result is exactly that of the bound without the field candidates."""
    base = Options(position_select=(0.3,), position_select_rounds=True)
    est = calibrate(walk, Options(position_select=(0.3,), position_select_rounds=True,
                                  position_select_field=(0.006, 0.012), position_select_field_rounds=True),
                    allow_weak=True)
    rec = [h["position_select_field"] for h in est.info["history"] if "position_select_field" in h]
    assert len(rec) == 1 and len(rec[0]["scores"]) >= 2
    sy = [s["field_sigma"][1] for s in rec[0]["scores"]]
    assert sy[0] == pytest.approx(np.broadcast_to(np.asarray(Options().field_sigma, float), (3,))[1])
    assert all(b > a for a, b in zip(sy, sy[1:]))
    if rec[0]["chosen"][1] == pytest.approx(sy[0]):
        np.testing.assert_array_equal(est.quat, calibrate(walk, base, allow_weak=True).quat)
    else:
        assert est.info["final_field_sigma"][1] == pytest.approx(rec[0]["chosen"][1])
