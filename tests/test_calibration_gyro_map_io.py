"""The gyro scale/misalignment E in calibration.json (an added field, DESIGN.md contract kept) and in
`Calibration.corrected_gyro`: round trip, files without the field, malformed fields, the equation."""

import json

import numpy as np
import pytest

from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.io.writers import read_calibration_json, write_calibration_json

E = np.array([[0.004, -0.002, 0.001], [0.003, -0.005, 0.0], [0.0, 0.002, 0.006]])


def _cal(**kw) -> Calibration:
    return Calibration(D=np.diag([50.0, 48.0, 52.0]), o=np.array([1.0, -2.0, 3.0]), dip_deg=60.0,
                       gyro_bias=np.array([0.01, 0.0, -0.02]), **kw)


def test_gyro_map_round_trips_through_calibration_json(tmp_path):
    path = write_calibration_json(tmp_path / "calibration.json", _cal(gyro_map=E))
    raw = json.loads(path.read_text())
    assert np.array_equal(np.array(raw["gyro_map"]), E)                  # 3×3 rows, as D
    for key in ("D", "o", "dip_deg", "gyro_bias", "noise", "std", "coverage", "converged", "iterations"):
        assert key in raw                                                 # the contract's fields stay
    back = read_calibration_json(path)
    assert np.array_equal(back.gyro_map, E)


def test_calibration_json_without_gyro_map_reads_as_zero(tmp_path):
    d = _cal().to_dict()
    d.pop("gyro_map")
    path = tmp_path / "old.json"
    path.write_text(json.dumps(d))
    cal = read_calibration_json(path)
    assert np.array_equal(cal.gyro_map, np.zeros((3, 3)))
    y = np.random.default_rng(0).normal(size=(5, 3))
    assert np.array_equal(cal.corrected_gyro(y), y)


@pytest.mark.parametrize("bad", [[1.0, 2.0, 3.0], [[0.0] * 3] * 2 + [[None, 0.0, 0.0]], "abc"])
def test_malformed_gyro_map_is_a_one_line_session_error(tmp_path, bad):
    d = _cal().to_dict()
    d["gyro_map"] = bad
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(SessionError) as info:
        read_calibration_json(path)
    msg = str(info.value)
    assert "\n" not in msg and "gyro_map" in msg and str(path) in msg


def test_corrected_gyro_is_one_plus_e_times_the_reading():
    """ω + b = (I + E)·b_gyr, written out per component (independent of the vectorised code)."""
    y = np.random.default_rng(1).normal(size=(4, 3))
    got = _cal(gyro_map=E).corrected_gyro(y)
    want = np.array([[sum(((i == j) + E[i, j]) * row[j] for j in range(3)) for i in range(3)] for row in y])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
