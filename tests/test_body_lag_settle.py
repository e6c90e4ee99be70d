"""(A2) of imugraph.graphs.body_lag_settle: the fixed lag's bootstrap extended until its placements settle (helper L22)."""

import numpy as np

from imugraph.graphs.body_lag_settle import settled_bootstrap_s


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _halving(calls):
    """Sensor A's bRs is Rz(−10°·0.5^(t−5)) (each second's step half the last), B's stays."""
    def solve(t):
        calls.append(t)
        return {"A": (_rz(np.deg2rad(-10.0 * 0.5 ** (t - 5.0))), np.zeros(3)), "B": (np.eye(3), np.zeros(3))}
    return solve


def test_settle_extends_until_no_sensor_moves_by_the_threshold():
    calls = []
    # A's steps from t−1 to t = 6, 7, …: 5, 2.5, 1.25, 0.625, 0.3125, 0.156° → the first below 0.3° is at 11 s
    t, info = settled_bootstrap_s(_halving(calls), 5.0, 30.0, 0.3, 1.0)
    assert t == 11.0 and info["settled"]
    assert calls == [5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0]
    assert np.allclose(info["settle_changes_deg"], [5.0, 2.5, 1.25, 0.625, 0.3125, 0.15625])


def test_settle_stops_a_step_before_the_session_ends_unsettled():
    calls = []
    t, info = settled_bootstrap_s(_halving(calls), 5.0, 8.0, 0.3, 1.0)
    assert t == 7.0 and not info["settled"]              # never the whole session: the stream needs data left
    assert calls == [5.0, 6.0, 7.0]
