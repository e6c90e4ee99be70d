"""Tests of the peer wiring (benchmarks/peers.py, benchmarks/common.py).

Synthetic tests always run; the BROAD tests skip when ../shared/data (or $IMUGRAPH_DATA) lacks the trial.
On trials 01 and 06 offline VQF must score below 2° (the data README: offline VQF 1.02° mean over the
17 trials), which checks the metric and the peer wiring together.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `benchmarks` is a folder, not installed

from benchmarks.common import broad_trials, load_broad_trial, print_table, trial_groups
from benchmarks.peers import ellipsoid_calibrated_mag, fit_ellipsoid, hold_mag, timed, vqf_offline, vqf_online
from imugraph.config import broad_dir
from imugraph.errors import ImugraphError
from imugraph.evaluate import field_norm_error, orientation_error
from imugraph.geometry import quat_to_rotmat
from imugraph.io.session import Session

pytest.importorskip("vqf")


def _trial(stem: str):
    path = broad_dir() / f"{stem}.mat"
    if not path.is_file():
        pytest.skip(f"BROAD trial {path} not present")
    return load_broad_trial(path)


def test_hold_mag_repeats_last_sample_and_fills_the_start():
    mag = np.full((6, 3), np.nan)
    mag[2] = [1.0, 2.0, 3.0]
    mag[4] = [4.0, 5.0, 6.0]
    held = hold_mag(mag)
    np.testing.assert_array_equal(held[:, 0], [1.0, 1.0, 1.0, 1.0, 4.0, 4.0])
    assert held.flags["C_CONTIGUOUS"] and held.dtype == np.float64
    assert np.isnan(mag[0, 0])  # input untouched
    with pytest.raises(ImugraphError, match="mag"):
        hold_mag(np.full((3, 3), np.nan))


def test_ellipsoid_fit_recovers_a_known_distortion():
    rng = np.random.default_rng(1)
    u = rng.normal(size=(2000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    D = np.array([[40.0, 3.0, -2.0], [1.0, 50.0, 4.0], [0.5, -1.0, 45.0]])
    o = np.array([10.0, -20.0, 5.0])
    b_mag = u @ D.T + o + 0.01 * rng.normal(size=u.shape)
    C, o_fit = fit_ellipsoid(b_mag)
    np.testing.assert_allclose(o_fit, o, atol=0.05)
    assert field_norm_error((b_mag - o_fit) @ C.T) < 1e-3
    session = Session(t=np.arange(2000) / 100.0, gyr=np.zeros((2000, 3)), acc=np.zeros((2000, 3)), mag=b_mag)
    assert field_norm_error(ellipsoid_calibrated_mag(session)) < 1e-3


def test_ellipsoid_fit_rejects_degenerate_data():
    with pytest.raises(ImugraphError):
        fit_ellipsoid(np.ones((5, 3)))


def test_timed_returns_result_and_seconds():
    out, sec = timed(sum, [1, 2, 3])
    assert out == 6 and sec >= 0.0


def test_print_table_aligns_columns(capsys):
    text = print_table([{"a": "x", "b": 1.234}, ["long name", 10.0]], ["a", "b"])
    lines = text.splitlines()
    assert len(lines) == 4 and len({len(line) for line in lines}) == 1
    assert "1.23" in capsys.readouterr().out


def test_broad_listing_and_groups():
    if not (broad_dir() / "trials.json").is_file():
        pytest.skip("BROAD trials.json not present")
    groups = trial_groups()
    assert groups["rotation"] == list(range(1, 10))
    assert 32 in groups["attached_magnet"] and 32 in groups["disturbed"] and 32 not in groups["undisturbed"]
    assert [p.name[:2] for p in broad_trials()][:3] == ["01", "02", "04"]


@pytest.mark.parametrize("stem", ["01_undisturbed_slow_rotation_A", "06_undisturbed_fast_rotation_A"])
def test_offline_vqf_scores_like_the_published_peer(stem):
    session = _trial(stem)
    assert session.quat is not None and session.movement is not None
    rms = {}
    for name, fn in {"VQF": vqf_online, "offline VQF": vqf_offline}.items():
        quat = fn(session)
        assert quat.shape == (session.n, 4)
        score = orientation_error(quat, session.quat, session.movement, session.rate)
        rms[name] = score.rms_deg
        print(f"{stem}: {name} {score.rms_deg:.3f}° shift {score.shift_samples:+.2f} samples "
              f"heading offset {score.heading_offset_deg:.1f}°")
        assert abs(score.shift_samples) <= 2.0
    assert rms["offline VQF"] < 2.0
    assert rms["VQF"] < 3.0
    assert rms["offline VQF"] < rms["VQF"]  # acausal smoothing helps on these trials


def test_vqf_nav_frame_puts_the_horizontal_field_along_x():
    session = _trial("01_undisturbed_slow_rotation_A")
    nRb = quat_to_rotmat(vqf_offline(session))
    n_mag = np.einsum("kij,kj->ki", nRb, session.mag)  # µT in nav: ≈ [15.6, 0, −41.4] (README, in ENU y)
    mean = np.nanmean(n_mag, axis=0)
    assert mean[0] > 10.0 and abs(mean[1]) < 2.0 and mean[2] < -35.0
    enu = np.nanmean(np.einsum("kij,kj->ki", quat_to_rotmat(vqf_offline(session, enu=True)), session.mag), 0)
    assert enu[1] > 10.0 and abs(enu[0]) < 2.0
