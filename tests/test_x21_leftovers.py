"""Session 21, helper X21: four leftovers of the acceptance run (docs/formats.md "x-IMU3 body sessions and four
leftovers"). Each test fails on the code before the fix. Inputs are simulated or built in tmp_path; the last test
loads the shared recordings (skipped when absent)."""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
import pytest

from imugraph.commands import common
from imugraph.errors import ImugraphError, SessionError
from imugraph.io.validate import validate_session
from imugraph.sim.scenario import distorted_session


@pytest.fixture(scope="module")
def sim():
    return distorted_session(3, duration_s=20.0, rate_hz=50.0)[0]


# ------------------------------------------------------------ (1) stream_orientation.png: truth or reference
def test_stream_orientation_legend_names_the_reference_as_the_console_does(tmp_path, sim):
    from imugraph.io.stream_figures import plot_stream_orientation

    onboard = replace(sim, meta=dict(sim.meta, quat_source="x-IMU3 onboard AHRS (estimate, not ground truth)"))
    q = np.asarray(sim.quat, float)
    for session, want in ((sim, "filtered vs truth"), (onboard, "filtered vs reference [x-IMU3 onboard AHRS")):
        fig = plot_stream_orientation(tmp_path / "o.png", sim.t, q, q, q, title="t",
                                      reference_label=common.reference_label(session))
        labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert any(lab.startswith(want) for lab in labels), labels
    fig = plot_stream_orientation(tmp_path / "o.png", sim.t, q, q, q)          # default: unchanged
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()][0].startswith("filtered vs reference, RMS")


# ------------------------------------------------------------ (2) diagnose: no empty --out after a failure
def _diag_args(session, out):
    return argparse.Namespace(session=str(session), out=str(out), quiet=True, data_dir=None, keyframe_hz=5.0,
                              seed=0, effects=None)


def test_diagnose_failed_run_leaves_no_empty_out_folder(tmp_path, monkeypatch, sim):
    import imugraph.diagnose.run as R
    from imugraph.commands.diagnose import run_diagnose

    path = tmp_path / "s.npz"
    np.savez(path, t=sim.t, gyr=sim.gyr, acc=sim.acc, mag=sim.mag)

    def fail(*a, **kw):
        raise ImugraphError("the diagnosis failed")

    monkeypatch.setattr(R, "diagnose", fail)
    out = tmp_path / "new" / "deeper"
    with pytest.raises(ImugraphError):
        run_diagnose(_diag_args(path, out))
    assert not (tmp_path / "new").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    with pytest.raises(ImugraphError):
        run_diagnose(_diag_args(path, kept))
    assert kept.is_dir()                                          # a folder the user made stays


def test_diagnose_body_failed_run_leaves_no_empty_out_folder(tmp_path, monkeypatch):
    import imugraph.diagnose.body.run as BR
    from imugraph.body.skeleton import lower_body
    from imugraph.commands.diagnose import run_diagnose
    from imugraph.geometry import expmap, rotmat_to_quat
    from imugraph.io.body_session import write_body_session
    from imugraph.sim.body import BodyMotion, random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    skel = lower_body()
    t = np.arange(0, 3.0, 0.02)
    rv = np.zeros((t.size, len(skel.names), 3))
    rv[:, :, 1] = 0.3 * np.sin(2 * np.pi * 0.8 * t)[:, None]
    q = rotmat_to_quat(expmap(rv))
    motion = BodyMotion(t, skel.names, q, skel.forward_kinematics(q, np.zeros((t.size, 3))))
    rng = np.random.default_rng(0)
    bs = simulate_body(motion, skel, random_placements(skel, rng), SensorParams(), rng)
    folder = write_body_session(tmp_path / "body", bs)

    def fail(*a, **kw):
        raise ImugraphError("the body diagnosis failed")

    monkeypatch.setattr(BR, "diagnose_body", fail)
    out = tmp_path / "new_body"
    with pytest.raises(ImugraphError):
        run_diagnose(_diag_args(folder, out))
    assert not out.exists()


# ------------------------------------------------------------ (3) a dead gyroscope is refused at load
@pytest.mark.parametrize("value", [0.0, 0.02])
def test_dead_gyroscope_refused(sim, value):
    gyr = np.array(sim.gyr, float)
    gyr[:, 1] = value                                              # one axis dead (zero) or frozen
    if value == 0.0:
        gyr[:] = 0.0                                               # all zero
    with pytest.raises(SessionError) as e:
        validate_session(replace(sim, gyr=gyr))
    assert e.value.field == "gyr"
    assert ("dead or disconnected gyroscope" in str(e.value)) if value == 0.0 else ("saturated" in str(e.value))


def test_gyroscope_at_rest_is_noise_not_constant(sim):
    """A sensor lying still: bias plus white noise at 0.005 rad/s passes (only an exactly constant axis fails)."""
    rng = np.random.default_rng(1)
    gyr = np.array([0.003, -0.002, 0.001]) + 0.005 * rng.standard_normal(sim.gyr.shape)
    still = replace(sim, gyr=gyr, acc=np.tile(sim.acc[:1], (sim.n, 1)) + 0.02 * rng.standard_normal(sim.acc.shape))
    assert validate_session(still, skip=("units",)) is still


# ------------------------------------------------------------ (4) imugraph CSV with ';' or tabs
def _write_csv(path, s, sep, decimal="."):
    head = ["t", "gyr_x", "gyr_y", "gyr_z", "acc_x", "acc_y", "acc_z", "mag_x", "mag_y", "mag_z"]
    data = np.column_stack([s.t, s.gyr, s.acc, s.mag])
    rows = [sep.join(f"{v:.9f}".replace(".", decimal) for v in r) for r in data]
    path.write_text(sep.join(head) + "\n" + "\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize("sep,decimal", [(";", "."), (";", ","), ("\t", "."), ("\t", ",")])
def test_imugraph_csv_with_semicolons_or_tabs(tmp_path, sim, sep, decimal):
    from imugraph.io.readers import load_session

    ref = load_session(_write_csv(tmp_path / "comma.csv", sim, ","))
    got = load_session(_write_csv(tmp_path / "other.csv", sim, sep, decimal))
    for k in ("t", "gyr", "acc", "mag"):
        np.testing.assert_array_equal(getattr(got, k), getattr(ref, k))


# ------------------------------------------------------------ every real recording still loads
def test_real_recordings_still_load(data_dir):
    from imugraph.io.body_session import read_body_session
    from imugraph.io.readers import load_session

    files = sorted((data_dir / "broad").glob("*.mat")) + sorted((data_dir / "gaittoolbox" / "rawimu").glob("*.txt"))
    if not files:
        pytest.skip("no BROAD or gaittoolbox files")
    for f in files:
        s = load_session(f)
        assert s.n > 1000 and np.all(np.std(s.gyr, axis=0) > 0)
    assert read_body_session(data_dir / "gaittoolbox" / "rawimu").n == 2503
