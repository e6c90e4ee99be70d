"""`imugraph batch` on a 2-process local Dask cluster, against each session run alone.

Sessions are short simulations (`distorted_session`) written as NPZ into tmp_path, so no shared data
are needed. Expected values come from the single-session `calibrate` command and from the simulator's
truth, never from the batch code under test.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json

import numpy as np
import pytest

from imugraph.cli import main
from imugraph.evaluate import orientation_error
from imugraph.sim.scenario import distorted_session

SEEDS, DURATION, RATE = (11, 12), 30.0, 50.0
FILES = ("calibration.json", "orientation.npz", "calibration.png", "heading.png")


def _run(argv: list[str]) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(argv)
    return rc, out.getvalue()


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """Two simulated sessions and one broken file through `batch --workers 2`, and each good one alone."""
    root = tmp_path_factory.mktemp("batch")
    truth = {}
    for seed in SEEDS:
        session, _ = distorted_session(seed, DURATION, RATE)
        np.savez(root / f"sim{seed}.npz", gyr=session.gyr, acc=session.acc, mag=session.mag, t=session.t,
                 quat=session.quat)
        truth[f"sim{seed}"] = session
    (root / "broken.npz").write_text("this is not an npz archive\n")
    names = [f"sim{SEEDS[0]}", "broken", f"sim{SEEDS[1]}"]
    rc, stdout = _run(["batch", *[str(root / f"{n}.npz") for n in names], "--out", str(root / "out"),
                       "--workers", "2", "--quiet"])
    alone = {n: _run(["calibrate", str(root / f"{n}.npz"), "--out", str(root / "alone" / n), "--quiet"])[0]
             for n in truth}
    return {"root": root, "out": root / "out", "rc": rc, "stdout": stdout, "names": names, "truth": truth,
            "alone": alone}


def _summary(batch) -> dict:
    return json.loads((batch["out"] / "summary.json").read_text())


def test_failed_session_gives_exit_1_and_does_not_stop_the_others(batch):
    assert batch["rc"] == 1
    assert batch["alone"] == {n: 0 for n in batch["truth"]}
    rows = {r["session"]: r for r in _summary(batch)["sessions"]}
    assert [r["session"] for r in _summary(batch)["sessions"]] == batch["names"]   # order of the arguments
    assert {n: rows[n]["status"] for n in rows} == {"sim11": "ok", "broken": "failed", "sim12": "ok"}
    error = rows["broken"]["error"]
    assert "broken.npz" in error and "\n" not in error and "Traceback" not in error
    assert not (batch["out"] / "broken").exists()
    for name in batch["truth"]:
        assert rows[name]["error"] == ""
        for f in FILES:
            assert (batch["out"] / name / f).stat().st_size > 0, (name, f)
    # the printed table names every session, the failure and its error
    assert all(n in batch["stdout"] for n in batch["names"]) and "failed" in batch["stdout"]
    assert "2/3 sessions ok" in batch["stdout"]


@pytest.mark.parametrize("index", [0, 1])
def test_results_identical_to_each_session_alone(batch, index):
    name = f"sim{SEEDS[index]}"
    got, ref = batch["out"] / name, batch["root"] / "alone" / name
    assert json.loads((got / "calibration.json").read_text()) == json.loads((ref / "calibration.json").read_text())
    with np.load(got / "orientation.npz") as a, np.load(ref / "orientation.npz") as b:
        np.testing.assert_array_equal(a["t"], b["t"])
        np.testing.assert_array_equal(a["quat"], b["quat"])


def test_summary_error_vs_truth(batch):
    rows = {r["session"]: r for r in _summary(batch)["sessions"]}
    assert rows["broken"]["error_deg"] is None
    for name, session in batch["truth"].items():
        with np.load(batch["out"] / name / "orientation.npz") as z:
            expected = orientation_error(z["quat"], session.quat, None, RATE).rms_deg
        assert rows[name]["error_deg"] == pytest.approx(expected, rel=1e-6)
        assert rows[name]["error_deg"] < 1.0            # a clean 30 s simulation: well under a degree
        assert rows[name]["time_s"] > 0


def test_summary_csv_matches_json_and_no_temporary_files(batch):
    doc = _summary(batch)
    assert (doc["ok"], doc["failed"]) == (2, 1)
    with open(batch["out"] / "summary.csv", newline="") as fh:
        lines = list(csv.DictReader(fh))
    assert [(r["session"], r["status"]) for r in lines] == [(r["session"], r["status"]) for r in doc["sessions"]]
    for line, row in zip(lines, doc["sessions"]):
        if row["error_deg"] is None:
            assert line["error_deg"] == ""
        else:
            assert float(line["error_deg"]) == pytest.approx(row["error_deg"], abs=1e-3)
    leftovers = [p.name for p in batch["out"].rglob("*") if p.name.startswith(".")]
    assert leftovers == []


def test_existing_scheduler_and_exit_0(batch, tmp_path):
    """--scheduler ADDRESS: an already running cluster; every session ok → exit status 0."""
    from distributed import LocalCluster

    name = f"sim{SEEDS[0]}"
    with LocalCluster(n_workers=1, processes=True, threads_per_worker=1, dashboard_address=None) as cluster:
        rc, _ = _run(["batch", str(batch["root"] / f"{name}.npz"), "--out", str(tmp_path),
                      "--scheduler", cluster.scheduler_address, "--quiet"])
    assert rc == 0
    with np.load(tmp_path / name / "orientation.npz") as a, np.load(batch["out"] / name / "orientation.npz") as b:
        np.testing.assert_array_equal(a["quat"], b["quat"])


def test_unreachable_scheduler_is_one_line_error():
    from imugraph.batch import dask_client
    from imugraph.errors import SessionError

    with pytest.raises(SessionError, match="scheduler"):
        with dask_client("tcp://127.0.0.1:9", timeout_s=1.0):
            pass


def test_output_folders_disambiguate_equal_stems(tmp_path):
    from imugraph.batch import output_folders

    got = output_folders(["a/trial.mat", "b/trial.mat", "c/other.npz", "d/trial.hdf5"], tmp_path)
    assert [p.name for p in got] == ["trial", "trial_2", "other", "trial_3"]
    assert all(p.parent == tmp_path for p in got)
