"""Figures are written atomically as valid PNG files."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure

from imugraph.errors import ImugraphError
from imugraph.geometry import quat_mul, rotvec_to_quat
from imugraph.io.figures import heading_deg, plot_calibration, plot_heading
from imugraph.sim.scenario import distorted_session

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def sim():
    return distorted_session(2, duration_s=20.0, rate_hz=50.0)


def _assert_png(path, folder) -> None:
    assert path.exists() and path.stat().st_size > 1000
    assert path.read_bytes()[:8] == PNG_MAGIC
    assert sorted(p.name for p in folder.iterdir()) == [path.name]     # no temp files left


def test_plot_calibration_with_residuals(tmp_path, sim):
    session, truth = sim
    cal = truth.to_calibration().apply(session.mag)
    rng = np.random.default_rng(0)
    residuals = {c: rng.standard_normal((500, 3)) for c in ("gyr", "acc", "mag")}
    out = tmp_path / "calibration.png"
    fig = plot_calibration(out, session.mag, cal, session.t, residuals, whitened=True)
    assert isinstance(fig, Figure)
    _assert_png(out, tmp_path)
    titles = [ax.get_title() for ax in fig.axes]
    assert {"gyr residuals", "acc residuals", "mag residuals", "Field norm over time"} <= set(titles)


def test_plot_calibration_without_residuals_overwrites(tmp_path, sim):
    session, truth = sim
    cal = truth.to_calibration().apply(session.mag)
    out = tmp_path / "calibration.png"
    out.write_bytes(b"old")
    mag = session.mag.copy()
    mag[::3] = np.nan                                                  # multi-rate magnetometer
    plot_calibration(out, mag, cal, session.t, None)
    _assert_png(out, tmp_path)


def test_plot_calibration_bad_shape_names_field(tmp_path, sim):
    session, _ = sim
    with pytest.raises(ImugraphError, match="b_mag_cal"):
        plot_calibration(tmp_path / "x.png", session.mag, session.mag[:, :2], session.t)
    assert list(tmp_path.iterdir()) == []


def test_plot_heading(tmp_path, sim):
    session, truth = sim
    offset = rotvec_to_quat(np.array([0.0, 0.0, np.deg2rad(10.0)]))
    q_est = quat_mul(offset[None, :], truth.nRb)                       # 10° heading offset in nav
    q_ref = truth.nRb.copy()
    q_ref[:5] = np.nan                                                 # unknown reference rows
    out = tmp_path / "sub" / "heading.png"
    fig = plot_heading(out, session.t, q_est, q_ref)
    _assert_png(out, out.parent)
    assert len(fig.axes) == 2
    only = tmp_path / "heading_only.png"
    plot_heading(only, session.t, q_est)
    assert only.read_bytes()[:8] == PNG_MAGIC


def test_heading_deg_known_values():
    yaw = np.deg2rad([0.0, 30.0, -120.0, 179.0])
    q = rotvec_to_quat(np.stack([np.zeros(4), np.zeros(4), yaw], -1))
    np.testing.assert_allclose(heading_deg(q), [0.0, 30.0, -120.0, 179.0], atol=1e-9)
