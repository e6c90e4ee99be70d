"""benchmarks/batch_scaling.py's comparison of the 1- and 2-worker runs: bit for bit, not by the score alone."""

import json

import numpy as np

from benchmarks.batch_scaling import same_outputs


def _write(folder, D, quat):
    folder.mkdir(parents=True)
    (folder / "calibration.json").write_text(json.dumps({"D": D, "o": [0.0, 0.0, 0.0]}))
    np.savez(folder / "orientation.npz", t=np.arange(3.0), quat=quat)


def test_same_outputs_bit_for_bit(tmp_path):
    q = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    q_eps = q.copy()
    q_eps[1, 0] = np.nextafter(1.0, 0.0)               # one ulp: the same error score, not the same result
    _write(tmp_path / "a", [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], q)
    _write(tmp_path / "b", [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], q.copy())
    _write(tmp_path / "c", [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], q_eps)
    _write(tmp_path / "d", [[1.0, 0, 0], [0, 1, 0], [0, 0, 1.0000001]], q)
    row = {"status": "ok", "out": str(tmp_path / "a")}
    assert same_outputs(row, {"status": "ok", "out": str(tmp_path / "b")})
    assert not same_outputs(row, {"status": "ok", "out": str(tmp_path / "c")})
    assert not same_outputs(row, {"status": "ok", "out": str(tmp_path / "d")})
    failed = {"status": "failed", "out": "", "error": "x.npz: unreadable"}
    assert same_outputs(failed, dict(failed)) and not same_outputs(failed, {**failed, "error": "other"})
