"""Speed changes of the body diagnosis that must not change results (session 18, helper B).

* `body_init.integrate_gyro_sensors` (all sensors' strapdown integration at once) against the per-sample
  recursion q_{k+1} = q_k ⊗ Exp(ω_k dt_k) written here with scalar Python arithmetic, and against
  imugraph.geometry.integrate_gyro (the function the body initial values used before): ≤ 1e-12 rad.
* the cached base residuals of `effects.base.changed_columns` and the reused graph of `fit.refit_body_warm`:
  the same numbers as without the cache / with a freshly built graph.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from imugraph.geometry import integrate_gyro, quat_conj, quat_mul, quat_to_rotvec
from imugraph.graphs.body_init import integrate_gyro_sensors


def _recursion(gyr, dt, q0):
    """The strapdown recursion sample by sample in plain floats (the reference; no numpy in the loop)."""
    q = [float(v) for v in q0]
    nq = math.sqrt(sum(v * v for v in q))
    q = [v / nq for v in q]
    out = [list(q)]
    for k in range(gyr.shape[0] - 1):
        w = [float(gyr[k, i]) * float(dt[k]) for i in range(3)]
        th = math.sqrt(sum(v * v for v in w))
        c, s = math.cos(th / 2), (math.sin(th / 2) / th if th > 1e-12 else 0.5)
        b = [c, w[0] * s, w[1] * s, w[2] * s]
        a = q
        q = [a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
             a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
             a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
             a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]]
        out.append(q)
    out = np.array(out)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _angle(qa, qb):
    """(N,) rotation angle between two quaternion paths, rad."""
    return np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(qa), qb)), axis=1)


def test_vectorised_integration_equals_the_per_sample_recursion():
    rng = np.random.default_rng(3)
    n, S = 3000, 5
    gyr = [rng.normal(0.0, 3.0, (n, 3)) + rng.normal(0.0, 1.0, 3) for _ in range(S)]    # up to ~10 rad/s
    dt = [np.full(n, 0.01) + rng.uniform(-1e-4, 1e-4, n) for _ in range(S)]           # jittered sample times
    q0 = [rng.normal(size=4) for _ in range(S)]
    got = integrate_gyro_sensors(gyr, dt, q0)
    assert len(got) == S
    for s in range(S):
        ref = _recursion(gyr[s], dt[s], q0[s])
        assert got[s].shape == (n, 4)
        assert np.max(_angle(ref, got[s])) <= 1e-12
        # the function the body initial values called before: the same operations, bit for bit
        old = integrate_gyro(gyr[s], dt[s], q0[s])
        assert np.array_equal(old, got[s])


def test_vectorised_integration_turns_at_the_given_rate():
    """Independent of any recursion: a constant rate ω about z for N samples turns by |ω| Σ dt."""
    n = 500
    w = np.tile([0.0, 0.0, 2.0], (n, 1))
    dt = np.full(n, 0.01)
    q = integrate_gyro_sensors([w], [dt], [np.array([1.0, 0.0, 0.0, 0.0])])[0]
    yaw = 2.0 * np.arctan2(q[:, 3], q[:, 0])
    expect = 2.0 * 0.01 * np.arange(n)
    assert np.max(np.abs(np.angle(np.exp(1j * (yaw - expect))))) < 1e-12


@pytest.fixture(scope="module")
def base_fit():
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_diagnose_body import _session

    from imugraph.diagnose.body.fit import fit_body
    return fit_body(_session(8.0, seed=1))


def test_reused_graph_is_the_fresh_graph_of_the_changed_problem(base_fit):
    """graph_with_sensor (the base graph with one sensor's prior and IMU factors replaced) against full_graph
    of the same changed problem: the same keys factor by factor and the same error, factor by factor, at two
    different Values; and the warm refit on it reaches the same solution as on a freshly built graph."""
    from dataclasses import replace as dc_replace

    import gtsam

    from imugraph.diagnose.body.fit import graph_with_sensor, refit_body_warm
    from imugraph.diagnose.effects.base import replace_session
    from imugraph.diagnose.body.effects.base import with_sensor
    from imugraph.graphs.body import full_graph, optimize, sensor_pims
    from imugraph.graphs.body_model import sensor_setup

    bfit = base_fit
    pb0 = bfit.problem
    sensor = "RightLowerLeg"
    ses = bfit.session.sensors[sensor]
    rng = np.random.default_rng(7)
    changed = with_sensor(bfit.session, sensor, replace_session(ses, gyr=ses.gyr + rng.normal(0, 0.01, ses.gyr.shape),
                                                                 acc=ses.acc + 0.3), {}, name="changed")
    setups = dict(pb0.setups)
    setups[sensor] = sensor_setup(changed, pb0.skel, pb0.opts, pb0.npose_idx)[sensor]
    pims = dict(pb0.pims)
    pims[sensor] = sensor_pims(changed.sensors[sensor], setups[sensor], pb0.kf, pb0.opts)
    pb = dc_replace(pb0, session=changed, setups=setups, pims=pims, mag_dirs=None)
    fresh = full_graph(pb)
    reused = graph_with_sensor(bfit.graph, pb, sensor)
    assert reused is not None and reused.size() == fresh.size()
    assert abs(full_graph(pb0).error(bfit.values) - bfit.graph.error(bfit.values)) == 0.0   # base graph untouched
    for vals in (pb0.init, bfit.values):
        assert reused.error(vals) == fresh.error(vals)
        for i in range(fresh.size()):
            assert list(reused.at(i).keys()) == list(fresh.at(i).keys())
            assert reused.at(i).error(vals) == fresh.at(i).error(vals)
    assert fresh.error(bfit.values) != bfit.graph.error(bfit.values)       # the change is seen by the factors
    x_fresh, _ = optimize(pb, fresh, bfit.values)
    warm = refit_body_warm(bfit, changed, sensor)
    assert warm.graph is not None
    assert gtsam.Values(x_fresh).equals(warm.values, 0.0)


def test_cached_base_residuals_are_the_recomputed_ones(base_fit):
    """changed_columns' cached base residuals: equal to residuals_with, recomputed when the sensor's fit changes."""
    from dataclasses import replace

    from imugraph.diagnose.body.effects.base import base_residuals
    from imugraph.diagnose.body.fit import BodyFit, residuals_with

    bfit = base_fit
    name = "LeftUpperLeg"
    first = base_residuals(bfit, name)
    assert base_residuals(bfit, name) is first                                    # cached
    ref = residuals_with(bfit, name)
    assert all(np.array_equal(first[c], ref[c]) for c in ref)
    sf = bfit.sensors[name]
    other = BodyFit(bfit.session, bfit.result, bfit.kf, dict(bfit.sensors, **{name: replace(sf, b_acc=sf.b_acc + 0.1)}),
                    bfit.g, bfit.info)                                            # the same info dict: shared cache
    moved = base_residuals(other, name)
    assert not np.allclose(moved["acc"], first["acc"])
    assert all(np.array_equal(moved[c], residuals_with(other, name)[c]) for c in moved)


def test_keyframe_options_are_exclusive(base_fit):
    from imugraph.diagnose.body.run import BodyDiagnoseOptions, diagnose_body

    with pytest.raises(ValueError, match="exclusive"):
        diagnose_body(base_fit.session, BodyDiagnoseOptions(keyframe_every=10, keyframe_s=0.1))
