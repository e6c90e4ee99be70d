"""The stream's figures (imugraph.io.stream_figures) and the per-sample error series they plot."""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.evaluate import orientation_error, orientation_error_series
from imugraph.geometry import quat_mul, rotvec_to_quat
from imugraph.io.stream_figures import plot_stream_calibration, plot_stream_orientation, plot_stream_timing

PNG = b"\x89PNG\r\n\x1a\n"


def _quats(n: int, seed: int, scale: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rotvec_to_quat(np.cumsum(rng.normal(scale=scale, size=(n, 3)), axis=0))


def test_error_series_is_the_score_per_sample():
    """The series' RMS is orientation_error's RMS (same shift, same heading offset, same samples)."""
    ref = _quats(800, 0, 0.02)
    est = quat_mul(rotvec_to_quat(np.array([0.0, 0.0, 0.4])), quat_mul(ref, _quats(800, 1, 0.002)))
    mask = np.arange(800) > 100
    idx, err = orientation_error_series(est, ref, mask)
    score = orientation_error(est, ref, mask, 100.0)
    assert idx.size == score.n and np.all(mask[idx])
    assert np.sqrt(np.mean(err ** 2)) == pytest.approx(score.rms_deg, rel=1e-9)
    assert err.max() == pytest.approx(score.max_deg, rel=1e-9)


def _history(n: int) -> list:
    rows = []
    for i in range(n):
        s = 10.0 / (1 + i)
        rows.append({"t": 2.0 * i, "D": (np.eye(3) * (50 + s)).tolist(), "o": [1.0, 2.0, 3.0 + s],
                     "dip_deg": 60.0 + s, "std": {"D": (np.full((3, 3), s)).tolist(), "o": [s] * 3, "dip_deg": s}})
    return rows


def test_figures_written_atomically_as_png(tmp_path):
    end = Calibration(D=np.eye(3) * 50.0, o=np.array([1.0, 2.0, 3.0]), dip_deg=60.0)
    plot_stream_calibration(tmp_path / "c.png", _history(20), end, reference=end)
    q = _quats(500, 2, 0.01)
    t = np.arange(500) / 100.0
    plot_stream_orientation(tmp_path / "o.png", t, q, quat_mul(q, _quats(500, 3, 0.001)), reference=q)
    plot_stream_orientation(tmp_path / "o2.png", t, q, q)               # no reference: filtered vs smoothed
    plot_stream_timing(tmp_path / "t.png", t[:50], np.linspace(1, 5, 50), np.linspace(1, 4, 50))
    for name in ("c.png", "o.png", "o2.png", "t.png"):
        assert (tmp_path / name).read_bytes()[:8] == PNG
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.png", "o.png", "o2.png", "t.png"]   # no temporaries


def test_bad_inputs_name_the_field(tmp_path):
    end = Calibration(D=np.eye(3), o=np.zeros(3), dip_deg=60.0)
    with pytest.raises(SessionError, match="calibration_history"):
        plot_stream_calibration(tmp_path / "c.png", [], end)
    with pytest.raises(SessionError, match="calibration_history"):
        plot_stream_calibration(tmp_path / "c.png", [{"t": 0.0, "D": [1, 2]}], end)
    with pytest.raises(SessionError, match="update_ms"):
        plot_stream_timing(tmp_path / "t.png", np.arange(3.0), np.arange(4.0))
    with pytest.raises(SessionError, match="smoothed"):
        plot_stream_orientation(tmp_path / "o.png", np.arange(5.0), _quats(5, 0, 0.1), _quats(4, 0, 0.1))
    assert not any(tmp_path.iterdir())
