"""stream_position: the bounded keyframe position of the stream (StreamOptions.position_sigma, eq. K1–K3)."""

import math

import gtsam
import numpy as np
import pytest

from imugraph import keys
from imugraph.errors import SessionError
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_lag import keyframe_group
from imugraph.graphs.stream_position import position_key, position_start, position_step
from imugraph.sim.scenario import distorted_session

RATE = 100.0


def test_rows_are_kinematics_and_gauss_markov():
    """The factor's cost is ½|(p_{k+1} − p_k − v_k Δt)/σ_kin|² + ½|(p_{k+1} − φ p_k)/σ_w|², written out here."""
    rng = np.random.default_rng(1)
    dt, sigma_p, tau_p, sigma_kin = 0.1, 0.3, 30.0, 1e-3
    f = position_step(4, dt, sigma_p, tau_p)
    p0, p1, v0 = rng.normal(0, 1, 3), rng.normal(0, 1, 3), rng.normal(0, 1, 3)
    vals = gtsam.Values()
    vals.insert(position_key(4), p0)
    vals.insert(position_key(5), p1)
    vals.insert(keys.vel(4), v0)
    phi = math.exp(-dt / tau_p)
    sig_w = sigma_p * math.sqrt(1 - phi**2)
    want = 0.5 * np.sum(((p1 - p0 - v0 * dt) / sigma_kin) ** 2) + 0.5 * np.sum(((p1 - phi * p0) / sig_w) ** 2)
    assert np.isclose(f.error(vals), want, rtol=1e-9)
    # (K3)
    start = position_start(sigma_p)
    v = gtsam.Values()
    v.insert(position_key(0), p0)
    assert np.isclose(start.error(v), 0.5 * np.sum((p0 / sigma_p) ** 2), rtol=1e-9)


def test_position_keys_group_with_their_keyframe():
    assert keyframe_group(position_key(17)) == 17
    assert keyframe_group(keys.vel(17)) == 17


def test_bad_sigma_raises(streamed):
    with pytest.raises(SessionError):
        StreamSmoother(streamed[None].cal, RATE, StreamOptions(lag_s=2.0, position_sigma=-1.0))


@pytest.fixture(scope="module")
def streamed():
    """A simulated 30 s session with a 0.5 s drop, streamed through the chain lag with and without the option."""
    session, truth = distorted_session(3, 30.0, RATE)
    cal = truth.to_calibration()
    drop = set(range(1500, 1550))
    out = {}
    for sigma in (None, 0.3):
        sm = StreamSmoother(cal, RATE, StreamOptions(lag_s=2.0, online_calibration=False, position_sigma=sigma),
                            g0=float(np.median(np.linalg.norm(session.acc, axis=1))))
        for i in range(session.n):
            if i not in drop:
                sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
        out[sigma] = sm
    return out


def test_off_by_default_and_on_in_the_window(streamed):
    """Default: no position key anywhere. On: every keyframe of the window has one, every update solved, and
    the estimate satisfies (K1) to well below σ_p (over the drop, Δt_k holds the missing time)."""
    off, on = streamed[None], streamed[0.3]
    assert StreamOptions().position_sigma is None
    assert not any(chr(k >> 56) == "p" for k in off._solver.stamps)
    assert off.stats.failed_updates == 0 and on.stats.failed_updates == 0
    est = on._solver.calculateEstimate()
    ks = sorted(k & ((1 << 56) - 1) for k in on._solver.stamps if chr(k >> 56) == "p")
    assert len(ks) >= 15 and ks[-1] == on._k
    t = np.asarray(on._kf_t)
    for k in ks[:-1]:
        dt = t[k + 1] - t[k]
        r = est.atVector(position_key(k + 1)) - est.atVector(position_key(k)) - est.atVector(keys.vel(k)) * dt
        assert np.linalg.norm(r) < 0.01
    assert on.stats.gaps == off.stats.gaps == 1


@pytest.mark.parametrize("solver", [{"lag_s": 2.0}, {"lag_s": None}, {"lag_s": 2.0, "fixed_lag_solver": "incremental"},
                                    {"lag_s": 2.0, "fixed_lag_solver": "batch"}])
def test_bounded_position_helps_a_sensor_that_stays_in_place(solver):
    """The simulation turns the sensor about a fixed point (no translation): the model's assumption holds, and
    the filtered error must drop clearly with it, under every solver (measured with the chain lag 0.34° → 0.18°)."""
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.stream_run import stream_session

    session, truth = distorted_session(3, 30.0, RATE)
    cal = truth.to_calibration()
    err = {}
    for sigma in (None, 0.3):
        r = stream_session(session, cal, StreamOptions(online_calibration=False, position_sigma=sigma, **solver))
        assert r.counts["failed_updates"] == 0
        err[sigma] = orientation_error(r.filtered, session.quat, None, RATE).rms_deg
    assert err[0.3] < 0.75 * err[None]


def test_position_select_off_by_default_and_the_stream_uses_the_bootstraps_choice():
    """StreamOptions.position_select (stream_run.select_position): off by default; on, the bootstrap batch's
    chosen σ_p (its info "position_sigma", one of the candidates or None for "off") is the stream's
    position_sigma, and stream_session gives exactly the stream run with that σ_p and that bootstrap."""
    from imugraph.graphs.stream_run import bootstrap_calibration, select_position, stream_session

    assert StreamOptions().position_select is None
    session, _ = distorted_session(3, 30.0, RATE)
    cands = (1e4, 1.0, 0.3)
    info: dict = {}
    opts = StreamOptions(lag_s=2.0, position_select=cands)
    cal, n_boot, chosen = select_position(session, opts, 20.0, info=info)
    assert chosen.position_sigma == info["position_sigma"]
    assert chosen.position_sigma is None or chosen.position_sigma in cands[1:]
    sel = [h["position_select"] for h in info["history"] if "position_select" in h]
    assert len(sel) == 1 and len(sel[0]["scores"]) == len(cands)
    # the default bootstrap is not the selecting one (different calibration options), but the same window
    _, n_plain = bootstrap_calibration(session, 20.0)
    assert n_boot == n_plain
    r = stream_session(session, None, opts, 20.0)
    ref = stream_session(session, None, chosen, 20.0, bootstrap=(cal, n_boot))
    assert r.bootstrap_samples == n_boot
    assert np.array_equal(r.filtered, ref.filtered) and np.array_equal(r.smoothed, ref.smoothed)
