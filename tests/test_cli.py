"""End-to-end tests of the `imugraph` command line, run in-process through `imugraph.cli.main`.

Expected values come from the simulator (`distorted_session` with the same seed, duration and rate as
the `simulate` command), never from the code under test.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from imugraph.cli import main
from imugraph.evaluate import orientation_error
from imugraph.sim.scenario import distorted_session

SEED, DURATION, RATE = 3, 40.0, 50.0
N = int(DURATION * RATE)
JSON_KEYS = {"D", "o", "dip_deg", "gyro_bias", "noise", "std", "coverage", "converged", "iterations"}


@pytest.fixture(scope="module")
def truth():
    session, truth = distorted_session(SEED, DURATION, RATE)
    return session, truth


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """simulate → calibrate → smooth --calibration, once for the module; returns paths and exit codes."""
    root = tmp_path_factory.mktemp("cli")
    session = root / "sim.npz"
    rc = {"simulate": main(["simulate", "--out", str(session), "--seed", str(SEED), "--duration", str(DURATION),
                            "--rate", str(RATE), "--quiet"])}
    rc["calibrate"] = main(["calibrate", str(session), "--out", str(root / "cal"), "--quiet"])
    rc["smooth"] = main(["smooth", str(session), "--calibration", str(root / "cal" / "calibration.json"),
                         "--out", str(root / "smooth"), "--quiet"])
    return {"root": root, "session": session, "cal": root / "cal", "smooth": root / "smooth", "rc": rc}


def test_commands_succeed_and_write_their_files(runs):
    assert runs["rc"] == {"simulate": 0, "calibrate": 0, "smooth": 0}
    for name in ("calibration.json", "orientation.npz", "calibration.png", "heading.png"):
        assert (runs["cal"] / name).stat().st_size > 0, name
    assert (runs["smooth"] / "orientation.npz").is_file()
    assert not (runs["smooth"] / "calibration.json").exists()     # a given calibration is not rewritten
    leftovers = [p.name for p in runs["root"].rglob("*") if p.name.startswith(".")]
    assert leftovers == []                                        # no temporary file survives


def test_simulated_file_is_the_simulator_session(runs, truth):
    session, _ = truth
    with np.load(runs["session"]) as z:
        for key in ("gyr", "acc", "mag", "t", "quat"):
            np.testing.assert_array_equal(z[key], getattr(session, key))


def test_calibration_json_contract_and_accuracy(runs, truth):
    _, true = truth
    d = json.loads((runs["cal"] / "calibration.json").read_text())
    assert JSON_KEYS <= set(d)
    assert set(d["noise"]) >= {"gyr", "acc", "mag"} and all(len(d["noise"][k]) == 3 for k in ("gyr", "acc", "mag"))
    assert np.shape(d["std"]["D"]) == (3, 3) and np.shape(d["std"]["o"]) == (3,)
    assert isinstance(d["converged"], bool) and isinstance(d["iterations"], int) and isinstance(d["coverage"], dict)
    D, o = np.array(d["D"]), np.array(d["o"])
    # field norm 50, magnetometer noise 0.5 per axis: the simulator's D and o within 1 %
    assert np.linalg.norm(D - true.D) / np.linalg.norm(true.D) < 0.01
    assert np.linalg.norm(o - true.o) < 0.01 * true.field_norm
    assert abs(d["dip_deg"] - true.dip_deg) < 0.5
    np.testing.assert_allclose(np.rad2deg(d["gyro_bias"]), np.rad2deg(true.gyro_bias), atol=0.1)  # °/s


@pytest.mark.parametrize("folder", ["cal", "smooth"])
def test_orientation_npz_contract_and_accuracy(runs, truth, folder):
    session, _ = truth
    with np.load(runs[folder] / "orientation.npz") as z:
        t, quat = z["t"], z["quat"]
    assert t.shape == (N,) and quat.shape == (N, 4)               # one row per input sample
    np.testing.assert_allclose(t, session.t)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-6)
    assert orientation_error(quat, session.quat, None, RATE).rms_deg < 1.0


def test_calibrate_prints_the_table(tmp_path, runs, capsys):
    assert main(["calibrate", str(runs["session"]), "--out", str(tmp_path), "--keyframe-hz", "5"]) == 0
    out, err = capsys.readouterr()
    for label in ("D", "o", "dip", "gyro bias °/s", "gyro map E", "noise mag", "converged", "field norm RMS",
                  "orientation"):
        assert f"\n  {label}" in out, label
    assert "calibrating" in err                                   # progress on stderr, not stdout
    assert "ML round 1" not in out                                # the ML loop's own lines too


def test_demo_end_to_end(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--duration", "30", "--rate", "50", "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    for name in ("calibration.json", "orientation.npz", "calibration.png", "heading.png"):
        assert (tmp_path / name).is_file(), name
    _, true = distorted_session(0, 30.0, 50.0)
    assert f"{true.D[0, 0]:.3f}" in out and f"{true.o[2]:.3f}" in out    # the simulator's truth is shown
    assert "estimated" in out and "field norm RMS" in out and "orientation" in out
    cal = json.loads((tmp_path / "calibration.json").read_text())
    assert np.linalg.norm(np.array(cal["D"]) - true.D) / np.linalg.norm(true.D) < 0.01


def _rest_session(path):
    rng = np.random.default_rng(1)
    np.savez(path, gyr=rng.normal(0, 0.01, (1500, 3)), acc=[0, 0, 9.81] + rng.normal(0, 0.05, (1500, 3)),
             mag=[20.0, 0.0, -40.0] + rng.normal(0, 0.5, (1500, 3)), rate=50.0)
    return path


@pytest.mark.parametrize("case", ["missing", "not_npz", "no_rotation", "bad_calibration", "short_sim"])
def test_bad_input_is_one_line_exit_2(tmp_path, runs, capsys, case):
    (tmp_path / "junk.npz").write_text("not a zip")
    argv = {
        "missing": ["calibrate", str(tmp_path / "absent.npz")],
        "not_npz": ["calibrate", str(tmp_path / "junk.npz")],
        "no_rotation": ["calibrate", str(_rest_session(tmp_path / "rest.npz"))],
        "bad_calibration": ["smooth", str(runs["session"]), "--calibration", str(tmp_path / "junk.npz")],
        "short_sim": ["simulate", "--out", str(tmp_path / "s.npz"), "--duration", "2"],
    }[case]
    assert main(argv + ["--quiet", "--out", str(tmp_path / "o")] if case != "short_sim" else argv + ["--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("imugraph: error: ") and err.count("\n") == 1 and "Traceback" not in err
    if case in ("missing", "not_npz", "bad_calibration"):
        assert ("absent.npz" if case == "missing" else "junk.npz") in err
    assert not (tmp_path / "s.npz").exists()


def test_interrupt_exits_130(monkeypatch, capsys):
    import imugraph.commands.simulate as simulate

    def interrupted(args):
        raise KeyboardInterrupt
    monkeypatch.setattr(simulate, "run_simulate", interrupted)
    assert main(["simulate", "--out", "never.npz"]) == 130
    assert "interrupted" in capsys.readouterr().err


def test_usage_errors_and_module_entry_point(tmp_path):
    assert main(["calibrate", "x.npz", "--keyframe-hz", "0"]) == 2
    assert main([]) == 2
    proc = subprocess.run([sys.executable, "-m", "imugraph.cli", "calibrate", str(tmp_path / "absent.npz"),
                           "--quiet"], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.startswith("imugraph: error: ") and proc.stderr.count("\n") == 1
    helped = subprocess.run([sys.executable, "-m", "imugraph.cli", "--help"], capture_output=True, text=True,
                            timeout=120)
    assert helped.returncode == 0 and "calibrate" in helped.stdout and "simulate" in helped.stdout


def test_calibrate_gyro_scale_flag_reaches_the_calibration(monkeypatch, tmp_path):
    """No flag follows the library default (ml.Options().gyro_map, on); `--gyro-scale` / `--no-gyro-scale`
    force it on / off, for calibrate and batch; both flags together are a usage error."""
    import imugraph.calibration.ml as ml
    from imugraph.cli import build_parser
    from imugraph.commands import calibrate as cmd

    seen = []

    def fake_calibrate(session, options, allow_weak=False):
        seen.append(options.gyro_map)
        raise RuntimeError("stop here")

    monkeypatch.setattr(ml, "calibrate", fake_calibrate)
    parser = build_parser()
    for command in (["calibrate", "x.npz"], ["batch", "x.npz", "--out", str(tmp_path)]):
        assert parser.parse_args(command + ["--gyro-scale"]).gyro_scale is True
        assert parser.parse_args(command + ["--no-gyro-scale"]).gyro_scale is False
        assert parser.parse_args(command).gyro_scale is None
        with pytest.raises(SystemExit):
            parser.parse_args(command + ["--gyro-scale", "--no-gyro-scale"])
    assert cmd.CalibrateOptions().gyro_scale is None
    progress = cmd.common.Progress(True)
    for flag in (True, False, None):
        try:
            cmd.estimate_calibration(None, 5.0, progress, gyro_scale=flag)
        except RuntimeError:
            pass
    assert seen == [True, False, ml.Options().gyro_map] and ml.Options().gyro_map is True
