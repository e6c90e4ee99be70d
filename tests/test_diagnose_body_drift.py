"""Body diagnosis, issue 5 follow-up: the graph extension of gyro_bias_drift (imugraph.diagnose.body.drift_graph),
the warm-started refits/simulations and the verdict rule (BV) with the shrink sign.

Sessions from tests/test_diagnose_body.py's analytic lower-body motion (independent of the BVH data).
"""

from __future__ import annotations

import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_diagnose_body import _session  # noqa: E402

from imugraph.diagnose.body.drift_graph import extended_graph, prescreen, refit_drift, segment_basis  # noqa: E402
from imugraph.diagnose.body.fit import fit_body, refit_body_warm  # noqa: E402
from imugraph.diagnose.body.run import verdict_of  # noqa: E402
from imugraph.diagnose.effects.base import replace_session  # noqa: E402
from imugraph.diagnose.body.effects.base import with_sensor  # noqa: E402


@pytest.fixture(scope="module")
def drifting():
    """(clean session, session with a linear 3 °/s drift on LeftUpperLeg's gyro about a known axis, β (N, 3))."""
    clean = _session(12.0, seed=2)
    ses = clean.sensors["LeftUpperLeg"]
    t = np.asarray(clean.t, float)
    axis = np.array([0.6, 0.0, 0.8])
    beta = np.deg2rad(3.0) * ((t - t[0]) / (t[-1] - t[0]))[:, None] * axis          # 3 °/s peak-to-peak
    new = replace_session(ses, gyr=ses.gyr + beta)
    return clean, with_sensor(clean, "LeftUpperLeg", new, {"injected": {"gyro_bias_drift": {}}}), beta


@pytest.fixture(scope="module")
def base_fit(drifting):
    return fit_body(drifting[1])


def test_drift_factor_is_the_whitened_walk_with_drift(base_fit):
    """(BD1): the LinearContainerFactor's error at random biases and coefficients equals
    ½‖(b_m − b_{m−1} − (β̄_m − β̄_{m−1}))/σ‖², computed here from the definition."""
    pb = base_fit.problem
    g, dkey = extended_graph(pb, "LeftUpperLeg")
    s = pb.names.index("LeftUpperLeg")
    first, dt, Bbar = segment_basis(pb)
    rng = np.random.default_rng(0)
    k0, k1 = pb.bkey(s, int(first[2])), pb.bkey(s, int(first[3]))
    found = [g.at(i) for i in range(g.size()) if g.at(i) is not None and tuple(g.at(i).keys()) == (k0, k1, dkey)]
    assert len(found) == 1 and isinstance(found[0], gtsam.LinearContainerFactor)
    b0, b1, c = rng.normal(0, 0.01, 6), rng.normal(0, 0.01, 6), rng.normal(0, 0.01, 9)
    v = gtsam.Values()
    v.insert(k0, gtsam.imuBias.ConstantBias(b0[:3], b0[3:]))
    v.insert(k1, gtsam.imuBias.ConstantBias(b1[:3], b1[3:]))
    v.insert(dkey, c)
    sig = np.r_[np.full(3, pb.opts.acc_bias_rw), np.full(3, pb.opts.bias_rw)] * np.sqrt(dt[2])
    drift = np.zeros(6)
    for p in range(3):                                       # c = (p, axis) flat: β̄ = Σ_p P̄_p c_p
        drift[3:] += (Bbar[3, p] - Bbar[2, p]) * c[3 * p:3 * p + 3]
    expected = 0.5 * np.sum(((b1 - b0 - drift) / sig) ** 2)
    assert found[0].error(v) == pytest.approx(expected, rel=1e-9)


def test_prescreen_ranks_the_drifting_sensor_first_and_the_refit_recovers_the_drift(base_fit, drifting):
    """(BD2) ranks LeftUpperLeg first; the (BD1) refit lowers the graph cost and recovers β's peak-to-peak
    (3 °/s injected, the base bias path alone held only part of it) within 30 %."""
    pre = {n: prescreen(base_fit, n) for n in base_fit.sensors}
    assert max(pre, key=lambda n: pre[n]["gain"]) == "LeftUpperLeg", pre
    theta, params = refit_drift(base_fit, "LeftUpperLeg")
    assert theta.info["cost_final"] < base_fit.info["cost_final"]
    assert params["peak_to_peak_deg_s"] == pytest.approx(3.0, rel=0.3)
    assert pre["LeftUpperLeg"]["ptp_deg_s"] < params["peak_to_peak_deg_s"]


def test_warm_refit_of_unchanged_data_stays_at_the_base_solution(base_fit, drifting):
    """fit.refit_body_warm with the sensor's measurements unchanged: the same graph from its own optimum, so the
    cost and the residuals stay (to the LM tolerance)."""
    theta = refit_body_warm(base_fit, drifting[1], "LeftUpperLeg")
    assert theta.info["cost_final"] <= base_fit.info["cost_final"] * (1 + 1e-3)
    r0, r1 = base_fit.sensors["LeftUpperLeg"].residuals["joint"], theta.sensors["LeftUpperLeg"].residuals["joint"]
    assert np.sqrt(np.mean((r1 - r0) ** 2)) < 0.05 * np.sqrt(np.mean(r0**2)) + 1e-6


def test_verdict_requires_a_shrinking_gap():
    """(BV): a significant, relevant candidate whose held-out gap grows (shrink < 0) is passed over for the next."""
    a = {"name": "soft_tissue", "sensor": "Pelvis", "significant": True, "relevant": True, "shrink": -0.06}
    b = {"name": "gyro_bias_drift", "sensor": "LeftFoot", "significant": True, "relevant": True, "shrink": 0.3}
    c = {"name": "soft_tissue", "sensor": "LeftFoot", "significant": False, "relevant": True, "shrink": 0.9}
    assert verdict_of([a, b, c]) == ("gyro_bias_drift", "LeftFoot")
    assert verdict_of([a, c]) == ("none", None)
    assert a["gap_shrinks"] is False and b["gap_shrinks"] is True
