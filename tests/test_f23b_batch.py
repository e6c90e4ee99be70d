"""U23 defect 9: `imugraph batch` into an existing --out, equal stems, a session given twice, a failed scheduler.

Folder names are written out by hand from the rule in docs/batch.md (never computed by the code under test); the
results of a session are compared with `imugraph calibrate` of the same file alone (the single-session command).
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json

import numpy as np
import pytest

from imugraph.cli import main
from imugraph.sim.scenario import distorted_session


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


# ---------------------------------------------------------------- folder names: from the paths, not their order
@pytest.mark.parametrize("paths,expected", [
    (["/d/a/trial.mat", "/d/b/trial.mat", "/d/c/other.npz", "/d/d/trial.hdf5"],
     ["a-trial", "b-trial", "other", "d-trial"]),
    (["/x/a/s.npz", "/y/a/s.npz", "/z/s.npz"], ["x-a-s", "y-a-s", "z-s"]),
    (["/x/s.npz", "/x/s.mat"], ["s-npz", "s-mat"]),                       # equal but for the extension
    (["/x/s.npz", "/x/s.mat", "/y/s.npz"], ["x-s-npz", "x-s-mat", "y-s"]),
    (["/x/S.npz", "/x/s.npz"], None),                                     # equal but for case: a hash each
    (["/x/S.npz", "/y/s.npz"], ["x-S", "y-s"]),                           # equal ignoring case
    (["/q/a/s.npz", "/r/b/s.npz", "/t/a-s.npz"], ["q-a-s", "b-s", "t-a-s"]),   # a suffix equal to another's stem
    (["/d/one.npz", "/d/two.npz"], ["one", "two"]),                       # distinct stems: the stem, as before
])
def test_path_names_are_unique_and_independent_of_the_order(paths, expected):
    from imugraph.batch import output_folders, path_names

    if expected is None:                        # names that differ, and differ from the plain stems
        expected = path_names(paths)
        assert len({n.casefold() for n in expected}) == len(paths) and not {"s", "S", "x-s", "x-S"} & set(expected)
    assert path_names(paths) == expected
    for order in itertools.permutations(range(len(paths))):
        assert path_names([paths[i] for i in order]) == [expected[i] for i in order]
    assert [p.name for p in output_folders(paths, "/out", "path")] == expected


def test_distinct_sessions_computes_a_file_once_however_spelled(tmp_path):
    from imugraph.batch import distinct_sessions

    (tmp_path / "a.npz").write_bytes(b"x")
    (tmp_path / "b.npz").write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "link.npz").symlink_to(tmp_path / "a.npz")
    a, b = str(tmp_path / "a.npz"), str(tmp_path / "b.npz")
    files, repeated = distinct_sessions([a, b, str(tmp_path / "sub" / ".." / "a.npz"), str(tmp_path / "link.npz"), b])
    assert files == [a, b]
    assert repeated == {a: 3, b: 2}


# ---------------------------------------------------------------- refusals: before any cluster starts
def test_non_empty_out_is_refused_in_one_line_before_any_work(tmp_path, capsys, monkeypatch):
    import imugraph.batch as batch

    def must_not_run(*a, **kw):
        raise AssertionError("run_batch called for a refused --out")

    monkeypatch.setattr(batch, "run_batch", must_not_run)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    rc, stdout, err = _run(["batch", str(tmp_path / "s.npz"), "--out", str(out)], capsys)
    assert rc == 2 and stdout == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("imugraph: error:") and "--overwrite" in lines[0], err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_failed_scheduler_leaves_no_out(tmp_path, capsys):
    for address in ("foo", "not an address"):
        out = tmp_path / "new" / "deeper"
        rc, _, err = _run(["batch", str(tmp_path / "s.npz"), "--out", str(out), "--scheduler", address, "--quiet"],
                          capsys)
        assert rc == 2 and "field 'scheduler'" in err, err
        assert not (tmp_path / "new").exists()


# ---------------------------------------------------------------- a real run, a refused re-run, an --overwrite re-run
@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """a/s.npz and b/s.npz (same stem), b given twice; then b alone into the same --out, refused and overwritten."""
    root = tmp_path_factory.mktemp("f23b_batch")
    for folder, seed in (("a", 11), ("b", 12)):
        session, _ = distorted_session(seed, 30.0, 50.0)
        (root / folder).mkdir()
        np.savez(root / folder / "s.npz", gyr=session.gyr, acc=session.acc, mag=session.mag, t=session.t,
                 quat=session.quat)
    a, b, out = str(root / "a" / "s.npz"), str(root / "b" / "s.npz"), root / "out"

    def run(argv):
        o, e = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
            rc = main(argv)
        return {"rc": rc, "out": o.getvalue(), "err": e.getvalue(),
                "ls": sorted(p.name for p in out.iterdir()) if out.exists() else None,
                "summary": json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else None}

    first = run(["batch", a, b, b, "--out", str(out), "--workers", "1"])
    first["b_cal"] = json.loads((out / "b-s" / "calibration.json").read_text())
    refused = run(["batch", b, "--out", str(out), "--workers", "1", "--quiet"])
    (out / "a-s" / "notes.txt").write_text("the user's own file\n")       # kept by --overwrite
    again = run(["batch", b, "--out", str(out), "--workers", "1", "--overwrite"])
    alone = root / "alone"
    assert main(["calibrate", b, "--out", str(alone), "--quiet"]) == 0
    return {"a": a, "b": b, "out": out, "first": first, "refused": refused, "again": again,
            "alone_cal": json.loads((alone / "calibration.json").read_text())}


def test_equal_stems_get_path_folders_and_a_repeat_runs_once(runs):
    first = runs["first"]
    assert first["rc"] == 0
    assert first["ls"] == ["a-s", "b-s", "summary.csv", "summary.json"]
    rows = first["summary"]["sessions"]
    assert [(r["path"], r["out"]) for r in rows] == [(runs["a"], str(runs["out"] / "a-s")),
                                                     (runs["b"], str(runs["out"] / "b-s"))]
    assert first["summary"]["repeated"] == {runs["b"]: 2}
    assert f"imugraph: note: {runs['b']} given 2 times: computed once" in first["err"]
    assert "2 sessions on a local cluster of 1 worker process " in first["err"]
    table = first["out"].splitlines()
    assert table[0].split()[:3] == ["session", "folder", "status"]
    assert [ln.split()[:3] for ln in table[2:4]] == [["s", "a-s", "ok"], ["s", "b-s", "ok"]]
    assert first["b_cal"] == runs["alone_cal"]                  # the same result as the session alone


def test_out_with_an_earlier_run_is_refused_and_left_as_it_was(runs):
    refused = runs["refused"]
    assert refused["rc"] == 2 and refused["out"] == ""
    assert len(refused["err"].strip().splitlines()) == 1 and "summary.json" in refused["err"]
    assert refused["ls"] == runs["first"]["ls"] and refused["summary"] == runs["first"]["summary"]


def test_overwrite_leaves_only_this_runs_sessions(runs):
    again = runs["again"]
    assert again["rc"] == 0
    # a-s held a file of the user's: kept with it alone; b-s (the earlier run's) removed; this run's b is in s/
    assert again["ls"] == ["a-s", "s", "summary.csv", "summary.json"]
    assert sorted(p.name for p in (runs["out"] / "a-s").iterdir()) == ["notes.txt"]
    assert [r["out"] for r in again["summary"]["sessions"]] == [str(runs["out"] / "s")]
    assert again["summary"]["overwrite"] == {"removed": ["b-s"], "kept": ["a-s"]}
    assert json.loads((runs["out"] / "s" / "calibration.json").read_text()) == runs["alone_cal"]
    assert "1 session on a local cluster of 1 worker process " in again["err"]
    assert "1 session folder of the earlier run removed; kept (other files in them): a-s" in again["err"]
