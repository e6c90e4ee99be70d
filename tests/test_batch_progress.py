"""`imugraph batch` without --quiet: the progress bar and the failed session's line on stderr, the summary
table on stdout (tests/test_batch.py runs everything else with --quiet). One broken file and one session
that cannot be found, so no calibration work is done: the cost is the 1-process local cluster."""

import re

from imugraph.cli import main


def test_progress_bar_and_failure_lines_on_stderr(tmp_path, capsys):
    broken = tmp_path / "broken.npz"
    broken.write_text("this is not an npz archive\n")
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    rc = main(["batch", str(broken), str(empty), "--out", str(tmp_path / "out"), "--workers", "1"])
    out, err = capsys.readouterr()
    assert rc == 1
    assert re.search(r"2/2 \[", err), err[-2000:]                # tqdm's final "2/2 [elapsed…]" on stderr
    assert re.search(r"broken: failed: \S*broken\.npz: field .file.", err), err[-2000:]   # tqdm.write: after a \r
    assert re.search(r"empty: failed: \S*empty\.npz: field .file.", err), err[-2000:]
    assert "Traceback" not in err
    # the summary table goes to stdout: one line per session with its status
    assert re.search(r"broken\s.*failed", out) and re.search(r"empty\s.*failed", out), out
    assert "0/2 sessions ok" in out
