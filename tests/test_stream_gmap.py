"""StreamOptions.gyro_map_end (imugraph.graphs.stream_gmap): the end-of-stream graph estimates the gyro map E.

Known answers: J_k and C_k against central differences of the interval's preintegrated rotation (the stream's own
preintegration, stream_interval.interval_preintegration, of the gyro corrected by (I + δE)); a simulated session
whose gyro has a known ~0.5 % scale/non-orthogonality: Ê recovers it and the smoothed output is closer to the truth
than with the option off; the coverage gate and the settling fallback give the plain end graph."""

import numpy as np
import pytest

from imugraph.evaluate import orientation_error
from imugraph.factors.gyro import exp_and_right_jacobian
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_gmap import equivalent_bias, map_jacobian_interval
from imugraph.graphs.stream_interval import interval_preintegration
from imugraph.io.session import Session
from imugraph.sim.scenario import distorted_session

RATE = 100.0
# symmetric (scale 0.4–0.6 %, non-orthogonality 0.1–0.3 %): the part E's data determine (its antisymmetric part, a
# rotation of the gyro axes against the accelerometer's, is held by the batch's tight prior σ_rot, gyro_map_block)
E_TRUE = np.array([[0.004, 0.002, 0.001], [0.002, -0.005, 0.003], [0.001, 0.003, 0.006]])
OPT = dict(online_calibration=False)


def _interval(seed: int = 0, n: int = 30):
    rng = np.random.default_rng(seed)
    t = np.r_[0.0, np.cumsum(np.full(n, 0.01) + rng.uniform(-1e-3, 1e-3, n))]
    w = rng.normal(0.0, 1.5, (n, 3))                  # up to ≈ 0.5 rad over the interval
    b = np.array([0.01, -0.02, 0.015])
    return t, w, b


def _pre(t, w, b):
    return interval_preintegration(t, w, np.zeros_like(w), b, np.full(3, 0.01), 0.0, np.full(3, 0.05), 0.0)


def _log(R):
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(R).as_rotvec()


def test_map_jacobian_numeric():
    """J_k of eq. (1) equals the central difference of Log(ΔR_kᵀ ΔR_k(δe)), ΔR_k(δe) preintegrated from (I + δE) ω."""
    t, w, b = _interval()
    kRb, dR, *_ = _pre(t, w, b)
    J = map_jacobian_interval(t, w, kRb, dR, b)
    eps, num = 1e-6, np.zeros((3, 9))
    for i in range(9):
        dE = np.zeros(9)
        dE[i] = eps
        dE = dE.reshape(3, 3)
        plus = _pre(t, w + w @ dE.T, b)[1]
        minus = _pre(t, w - w @ dE.T, b)[1]
        num[:, i] = _log(minus.T @ plus) / (2 * eps)
    assert np.allclose(J, num, rtol=1e-5, atol=1e-8)
    assert np.abs(J).max() > 1e-3                         # not a trivially zero Jacobian


def test_equivalent_bias_moves_super_sample_as_e():
    """C_k of eq. (2): the super-sample rotation Exp(θ̄ − Δt C_k δe) (gtsam's bias correction of the one-sample
    preintegration, stream.py _close) equals the interval preintegrated at (I + δE) to second order in δe."""
    t, w, b = _interval(1)
    kRb, dR, *_ = _pre(t, w, b)
    dt_k = t[-1] - t[0]
    C = equivalent_bias(map_jacobian_interval(t, w, kRb, dR, b), dR, dt_k)
    rng = np.random.default_rng(2)
    for scale in (1e-3, 1e-4):
        de = rng.normal(0.0, scale, 9)
        exact = _pre(t, w + w @ de.reshape(3, 3).T, b)[1]
        phi = _log(dR) - dt_k * (C @ de)                  # the factor's corrected tangent, bias b̂ + C_k δe
        from scipy.spatial.transform import Rotation
        model = Rotation.from_rotvec(phi).as_matrix()
        err = np.linalg.norm(_log(exact.T @ model))
        first = np.linalg.norm(_log(exact.T @ dR))        # the change δe makes at all
        assert err < 0.02 * first and err < 50 * scale**2


def _scaled(duration_s: float, seed: int = 3):
    s, truth = distorted_session(seed, duration_s, RATE)
    raw = np.linalg.solve(np.eye(3) + E_TRUE, s.gyr.T).T          # the sensor reports (I + E)⁻¹ ω
    scaled = Session(s.t, raw, s.acc, s.mag, s.quat, s.movement, s.source, s.name, s.meta)
    return s, scaled, truth.to_calibration()


def _run(session, cal, on: bool, max_contraction: float | None = None):
    sm = StreamSmoother(cal, RATE, StreamOptions(gyro_map_end=on, **OPT), g0=9.81)
    if max_contraction is not None:
        sm._gmap.max_contraction = max_contraction
    for i in range(session.n):
        sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
    sm.finish()
    return sm, sm.smoothed()


@pytest.fixture(scope="module")
def long_case():
    s, scaled, cal = _scaled(100.0)
    return s, scaled, cal, _run(scaled, cal, False), _run(scaled, cal, True)


def test_recovers_known_gyro_map(long_case):
    """100 s (≥ 15 clean turns): Ê within 0.1 % of every entry of the simulated E, settled; smoothed error vs the
    truth at most half of the option off's."""
    s, _, _, (sm_off, q_off), (sm_on, q_on) = long_case
    info = sm_on._gmap.info
    assert info["estimated"] and info["clean_turns"] >= 15.0
    E_hat = np.array(info["E"])
    assert np.abs(E_hat - E_TRUE).max() < 1e-3, (E_hat, E_TRUE)
    assert np.allclose(sm_on._gmap.total(sm_on._final), E_hat, atol=1e-4)     # the final LM keeps it
    assert np.allclose(sm_on.cal.gyro_map, sm_on._gmap.total(sm_on._final))   # calibration.json carries Ê
    assert not np.any(sm_off.cal.gyro_map)
    err_off = orientation_error(q_off, s.quat, None, RATE).rms_deg
    err_on = orientation_error(q_on, s.quat, None, RATE).rms_deg
    print(f"\nsimulated E: smoothed vs truth off {err_off:.3f}°, on {err_on:.3f}°; max |Ê − E| {np.abs(E_hat - E_TRUE).max():.2e}")
    assert err_on < 0.5 * err_off, (err_on, err_off)
    assert sm_off._gmap is None


def test_settling_fallback_is_the_plain_graph(long_case):
    """A settling gate no step can pass (max_contraction 0) falls back to E = Ê₀: the output of the option off."""
    _, scaled, cal, (_, q_off), _ = long_case
    sm, q = _run(scaled, cal, True, max_contraction=0.0)
    assert not sm._gmap.info["estimated"] and "settle" in sm._gmap.info["reason"]
    assert np.allclose(q, q_off, atol=1e-9)


def test_coverage_gate():
    """40 s (< 15 clean turns): E not estimated, the output of the option off exactly."""
    _, scaled, cal = _scaled(40.0)
    sm, q = _run(scaled, cal, True)
    _, q_off = _run(scaled, cal, False)
    assert not sm._gmap.info["estimated"] and sm._gmap.info["clean_turns"] < 15.0
    assert np.allclose(q, q_off, atol=1e-12)


def test_jr_convention():
    """The bias Jacobian eq. (2) assumes (gtsam's one-sample tangent preintegration): θ̄(b) = θ̄ − Δt δb."""
    import gtsam

    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    omega, dt, b = np.array([1.0, -2.0, 0.5]), 0.1, np.array([0.01, 0.02, -0.01])
    pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias(np.zeros(3), b))
    pim.integrateMeasurement(np.array([0.0, 0.0, 9.81]), omega, dt)
    db = np.array([1e-4, -2e-4, 3e-4])
    R = pim.predict(gtsam.NavState(), gtsam.imuBias.ConstantBias(np.zeros(3), b + db)).attitude().matrix()
    expected = gtsam.Rot3.Expmap((omega - b - db) * dt).matrix()
    assert np.allclose(R, expected, atol=1e-12)
    _, jr = exp_and_right_jacobian(((omega - b) * dt)[None])
    assert np.abs(jr[0] - np.eye(3)).max() > 1e-3            # the J_r of eq. (2) is not the identity here


def test_coverage_gate_is_the_batch_gate():
    """The running sums of the coverage gate (samples arriving interval by interval) equal calibration.gyro_map's
    clean_intervals + clean_turns on the batch's keyframe intervals (stride round(rate / Options.keyframe_hz))."""
    from types import SimpleNamespace

    from imugraph.calibration.gyro_map import clean_intervals, clean_turns
    from imugraph.calibration.options import Options
    from imugraph.graphs.stream_gmap import EndGyroMap

    rng = np.random.default_rng(5)
    n, g = 3000, 9.81
    acc = np.tile([0.0, 0.0, g], (n, 1)) + rng.normal(0.0, 0.3, (n, 3))
    acc[rng.choice(n, 40, replace=False)] *= 1.4                  # some fast-motion rows: | |a| − g | > 2 m/s²
    gyr = rng.normal(0.0, 2.0, (n, 3))
    t = np.r_[0.0, np.cumsum(np.full(n, 0.01))]
    owner = SimpleNamespace(rate=100.0, _g=g, cal=SimpleNamespace(gyro_map=np.zeros((3, 3))),
                            opt=SimpleNamespace(gyro_map_end=True))
    gm = EndGyroMap(owner)
    edges = np.r_[0, np.cumsum(rng.integers(5, 15, 400))]         # stream intervals of 5–14 samples
    edges = np.r_[edges[edges < n], n]
    for a, b in zip(edges[:-1], edges[1:]):
        dev = np.abs(np.linalg.norm(acc[a:b], axis=1) - g)
        gm._gate_rows(dev, np.linalg.norm(gyr[a:b], axis=1) * (t[a + 1:b + 1] - t[a:b]) / (2 * np.pi))
    gm._gate_close()
    stride = int(round(100.0 / Options().keyframe_hz))
    skf = np.arange(n) // stride
    clean = clean_intervals(acc, g, skf, int(skf.max()) + 1, Options().gyro_map_acc_tol)
    assert 0 < clean.sum() < len(clean)
    assert gm.turns == pytest.approx(clean_turns(gyr, np.full(n, 0.01), skf, clean), rel=1e-12)


# ---------------------------------------------------------------- gyro_map_end="exact" (session 19, helper Z)
def test_exact_repreintegration_is_the_streams():
    """"exact" keeps the samples: re-preintegrated with the batch's code (factors.gyro.preintegrate,
    gyro_map.map_jacobian) at Ê = Ê₀ (a start calibration WITH a gyro map, undone and re-applied, eq. 3) and the
    stream's b̂, every interval's ΔR_k and J_k equal the stream's own (stream_interval, map_jacobian_interval); at
    Ê₀ + δe, ΔR_k moves as ΔR_k Exp(J_k δe) to second order."""
    from dataclasses import replace

    _, scaled, cal = _scaled(20.0)
    cal = replace(cal, gyro_map=np.array([[0.003, 0.001, 0.0], [-0.002, 0.004, 0.001], [0.0, 0.002, -0.003]]))
    sm = StreamSmoother(cal, RATE, StreamOptions(gyro_map_end="exact", **OPT), g0=9.81)
    for i in range(scaled.n):
        sm.push(scaled.t[i], scaled.gyr[i], scaled.acc[i], scaled.mag[i])
    sm.finish()
    gm = sm._gmap
    K1 = len(sm._hist_dR)
    assert len(gm.rows) == K1 and len(gm.J) == K1
    b = np.tile(sm._b_hat, (K1, 1))
    dR, J, dv = gm.repreintegrate(np.zeros(9), b)
    assert np.abs(dR - np.array(sm._hist_dR)).max() < 1e-10
    assert np.abs(J - np.array([gm.J[k] for k in range(K1)])).max() < 1e-9
    assert dv.shape == (K1, 3) and np.all(np.isfinite(dv))
    de = np.random.default_rng(5).normal(0.0, 1e-3, 9)
    dR2, _, _ = gm.repreintegrate(de, b)
    first = max(np.linalg.norm(_log(dR[k].T @ dR2[k])) for k in range(K1))
    err = max(np.linalg.norm(_log((dR[k] @ _rotvec(J[k] @ de)).T @ dR2[k])) for k in range(K1))
    assert first > 1e-4 and err < 0.02 * first, (err, first)


def _rotvec(v):
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(v).as_matrix()


def test_exact_recovers_known_gyro_map(long_case):
    """"exact" on the 100 s simulation: Ê within 0.1 % of every entry, settled, smoothed error vs truth at most
    half of the option off's (the exact rounds on a near-linear problem: as the first-order ones)."""
    s, scaled, cal, (_, q_off), _ = long_case
    sm, q = _run(scaled, cal, "exact")
    info = sm._gmap.info
    assert info["estimated"] and info["exact"]
    E_hat = np.array(info["E"])
    assert np.abs(E_hat - E_TRUE).max() < 1e-3, (E_hat, E_TRUE)
    err_off = orientation_error(q_off, s.quat, None, RATE).rms_deg
    err_on = orientation_error(q, s.quat, None, RATE).rms_deg
    print(f"\nexact: smoothed vs truth off {err_off:.3f}°, exact {err_on:.3f}°; steps {info['steps']}; "
          f"{info['bytes_per_keyframe']:.0f} bytes per keyframe kept")
    assert err_on < 0.5 * err_off, (err_on, err_off)


@pytest.fixture(scope="module")
def theta_cases(long_case):
    """The 100 s simulation with the stream's default θ state (calib_states, windows_end): gyro_map_end True,
    "theta" (θ free in the E rounds), "theta_gate" (those rounds as the settling gate only) and "theta_e" (their Ê
    fixed in the θ-held end graph)."""
    s, scaled, cal, _, _ = long_case
    out = {}
    for mode in (True, "theta", "theta_gate", "theta_e"):
        sm = StreamSmoother(cal, RATE, StreamOptions(gyro_map_end=mode), g0=9.81)
        for i in range(scaled.n):
            sm.push(scaled.t[i], scaled.gyr[i], scaled.acc[i], scaled.mag[i])
        sm.finish()
        out[mode] = (sm, sm.smoothed())
    return s, out


def test_theta_free_rounds(theta_cases):
    """"theta": θ a variable of the E rounds (the stream_windows_end factors on θ): E still recovered within 0.1 %
    (θ = the truth's here, so freeing it costs nothing); "theta_gate" settled there, then the θ-held rounds: the
    output of gyro_map_end=True to 1e-9."""
    s, out = theta_cases
    info = out["theta"][0]._gmap.info
    assert info["estimated"] and info["theta_free"]
    assert np.abs(np.array(info["E"]) - E_TRUE).max() < 1e-3, info["E"]
    gate = out["theta_gate"][0]._gmap.info
    assert gate["estimated"] and gate["theta_check"]["steps"] and gate["theta_check"]["contraction"] <= 0.5
    assert np.allclose(out["theta_gate"][1], out[True][1], atol=1e-9)
    errs = {m: orientation_error(q, s.quat, None, RATE).rms_deg for m, (_, q) in out.items()}
    print(f"\ntheta modes, smoothed vs truth: {errs}")
    assert errs["theta"] < 1.5 * errs[True] + 0.05


def test_theta_e_fixes_the_theta_free_E(long_case, theta_cases):
    """"theta_e": the θ-free rounds' Ê (the same rounds as "theta": equal to 1e-12) recovers the simulated E within
    0.1 %, is held fixed — no e in the final graph, the calibration carries exactly it — and the smoothed output is
    at most half as far from the truth as with the option off."""
    s, _, _, (_, q_off), _ = long_case
    _, out = theta_cases
    sm, q = out["theta_e"]
    info = sm._gmap.info
    assert info["estimated"] and info["theta_e"] and info["theta_free"]
    E_hat = np.array(info["E"])
    assert np.allclose(E_hat, out["theta"][0]._gmap.info["E"], atol=1e-12)
    assert np.abs(E_hat - E_TRUE).max() < 1e-3, (E_hat, E_TRUE)
    from imugraph.graphs.gyro_map_block import E_KEY
    assert not sm._final.exists(E_KEY)
    assert np.allclose(sm.cal.gyro_map, E_hat, atol=1e-15)
    err_off = orientation_error(q_off, s.quat, None, RATE).rms_deg
    err_e = orientation_error(q, s.quat, None, RATE).rms_deg
    print(f"\ntheta_e: smoothed vs truth off {err_off:.3f}°, theta_e {err_e:.3f}°")
    assert err_e < 0.5 * err_off, (err_e, err_off)
