"""The stream uses the calibration's accelerometer timing δ (calibration/acc_timing.py) and velocity process σ_v, τ_v
(calibration/velocity_process.py) as `smooth_fixed` does: one model in the stream and the batch path."""

from dataclasses import replace

import numpy as np
import pytest

from imugraph.calibration.acc_timing import lead_accelerometer, with_lead
from imugraph.errors import SessionError
from imugraph.evaluate import orientation_error
from imugraph.graphs.cpp_smoother import smooth_fixed
from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_interval import lead_interval
from imugraph.graphs.stream_options import acc_lead, velocity_process
from imugraph.graphs.stream_run import stream_session
from imugraph.io.session import Session
from imugraph.sim.scenario import distorted_session

RATE = 100.0
FIXED = StreamOptions(online_calibration=False, field_sigma=None)
E = np.array([[0.01, -0.0087, 0.0], [0.0087, 0.0, 0.0], [0.0, 0.0, 0.03]])     # a gyro scale/misalignment


@pytest.fixture(scope="module")
def case():
    session, truth = distorted_session(5, 20.0, RATE)
    keep = np.ones(session.n, bool)
    keep[[300, 301, 302, 777]] = False          # gaps: uneven steps Δt_i, which eq. (3)/(4) use
    s = session.slice(0, session.n)
    s = Session(s.t[keep], s.gyr[keep], s.acc[keep], s.mag[keep], s.quat[keep], s.movement[keep],
                s.source, s.name, s.meta)
    return s, truth.to_calibration()


STRIDE = 10         # RATE / keyframe_hz: before the first keyframe the filtered output is the TRIAD of the first
# row as recorded (its re-timing needs the next row's time step), so the comparisons start at keyframe 1


def _push_all(cal, s, opt):
    sm = StreamSmoother(cal, RATE, opt, g0=9.81)
    return np.array([sm.push(s.t[i], s.gyr[i], s.acc[i], s.mag[i]) for i in range(s.n)])[STRIDE:]


@pytest.mark.parametrize("lead", [0.5, 1.0, 2.3])
@pytest.mark.parametrize("stride", [10, 1])
def test_lead_interval_is_lead_accelerometer(lead, stride):
    """Known answer: interval by interval (with the tail carried over), eq. (4) gives the rows of the batch
    function on the whole array (tail and first-row repeat included; stride 1: intervals shorter than δ)."""
    rng = np.random.default_rng(1)
    n = 95
    t = np.cumsum(rng.uniform(0.005, 0.02, n))
    w, a = rng.normal(0, 2.0, (n, 3)), rng.normal(0, 5.0, (n, 3))
    dt = np.append(np.diff(t), 0.0)
    want = lead_accelerometer(a, lead, w, dt)
    whole = int(np.floor(lead))
    tail, got = np.zeros((0, 3)), []
    for i0 in range(0, n - 1, stride):
        i1 = min(i0 + stride, n - 1)
        out, tail = lead_interval(t[i0:i1 + 1], w[i0:i1], a[i0:i1], tail, whole, lead - whole)
        got.append(out)
    assert np.allclose(np.concatenate(got), want[:n - 1], atol=1e-12)


@pytest.mark.parametrize("lead", [0.5, 1.5])
def test_stream_with_lead_equals_stream_of_led_session(case, lead):
    """Streaming the recorded rows with δ in the calibration (and a gyro map E) equals streaming the session
    re-timed beforehand by `acc_timing.with_lead` with δ = 0, sample by sample (filtered output)."""
    session, cal = case
    part = session.slice(0, 900)
    raw = Session(part.t, np.linalg.solve(np.eye(3) + E, part.gyr.T).T, part.acc, part.mag, part.quat,
                  part.movement, part.source, part.name, part.meta)
    led = with_lead(raw, lead)
    cal_e = replace(cal, gyro_map=E.copy())
    opt = StreamOptions(lag_s=1.0, online_calibration=False)
    q_lead = _push_all(replace(cal_e, acc_lead_samples=lead), raw, opt)
    q_pre = _push_all(replace(cal_e, acc_lead_samples=0.0), led, opt)
    assert np.allclose(q_lead, q_pre, atol=1e-9)
    # the options' δ overrides the calibration's
    q_opt = _push_all(replace(cal_e, acc_lead_samples=0.0), raw, replace(opt, acc_lead_samples=lead))
    assert np.allclose(q_opt, q_pre, atol=1e-9)
    # and δ matters: without it the output differs
    q_none = _push_all(replace(cal_e, acc_lead_samples=0.0), raw, opt)
    assert np.max(np.abs(q_none - q_pre)) > 1e-6


def test_velocity_process_from_calibration_or_options(case):
    """σ_v, τ_v: the options' where set, else the calibration's, else 0.5 m/s / 2 s; the stream's output with a
    calibration's σ_v, τ_v equals that with the same numbers set in the options."""
    session, cal = case
    assert velocity_process(StreamOptions(), cal) == (0.5, 2.0)
    cal_v = replace(cal, velocity_sigma=0.2, velocity_tau=0.7)
    assert velocity_process(StreamOptions(), cal_v) == (0.2, 0.7)
    assert velocity_process(StreamOptions(velocity_sigma=1.0), cal_v) == (1.0, 0.7)
    part = session.slice(0, 600)
    opt = StreamOptions(lag_s=1.0, online_calibration=False)
    q_cal = _push_all(cal_v, part, opt)
    q_opt = _push_all(cal, part, replace(opt, velocity_sigma=0.2, velocity_tau=0.7))
    q_def = _push_all(cal, part, opt)
    assert np.allclose(q_cal, q_opt, atol=1e-10)
    assert np.max(np.abs(q_cal - q_def)) > 1e-6


def test_bad_lead_or_velocity_process_raises(case):
    _, cal = case
    with pytest.raises(SessionError, match="acc_lead_samples"):
        StreamSmoother(replace(cal, acc_lead_samples=-0.5), RATE, FIXED)
    with pytest.raises(SessionError, match="acc_lead_samples"):
        StreamSmoother(cal, RATE, replace(FIXED, acc_lead_samples=float("nan")))
    with pytest.raises(SessionError, match="velocity_tau"):
        StreamSmoother(cal, RATE, replace(FIXED, velocity_tau=0.0))
    assert acc_lead(StreamOptions(), replace(cal, acc_lead_samples=2.25)) == (2, 0.25)


def test_smoothed_stream_is_smooth_fixed_with_lead_and_velocity_process(case):
    """One model, two solvers, with δ = 0.5 and an estimated-looking σ_v, τ_v in the calibration: iSAM2's
    smoothed output equals `smooth_fixed` with the same calibration (which applies both) within 0.1° RMS and
    well below the estimation error itself."""
    session, cal = case
    cal_x = replace(cal, acc_lead_samples=0.5, velocity_sigma=0.3, velocity_tau=1.5)
    batch = smooth_fixed(session, cal_x, keyframe_hz=FIXED.keyframe_hz, rotation_tol_deg=0.001)
    r = stream_session(session, cal_x, FIXED)
    gap = orientation_error(r.smoothed, batch, None, RATE, heading=False, max_shift=0.0).rms_deg
    batch_err = orientation_error(batch, session.quat, None, RATE).rms_deg
    assert gap < 0.1 and gap < 0.25 * batch_err
    assert r.counts["failed_updates"] == 0
