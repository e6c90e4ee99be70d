"""Every injected effect of the harness is above its own relevance level (docs/diagnose.md §3 table,
issue 5 G2 (d)): an injection below it would be a case the diagnoser must call "none".

The injected size is measured on the injected signal itself (injected − original session, or the truth
parameters), independently of the effects' `fit`/`size`, and compared with each module's threshold.
"""

from __future__ import annotations

import numpy as np
import pytest

from imugraph.diagnose.bench import simulated_session
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects import accelerometer_bias as acc_bias
from imugraph.diagnose.effects import gyro_bias_drift as drift
from imugraph.diagnose.effects import gyro_scale as gscale
from imugraph.diagnose.effects import magnetic_disturbance as magnet
from imugraph.diagnose.effects import saturation as sat
from imugraph.diagnose.effects import time_offset as toff
from imugraph.diagnose.effects import vibration as vib
from imugraph.diagnose.effects.linear_acceleration import STANDARD_G

DRAWS = 12


@pytest.fixture(scope="module", params=[285.714, 100.0], ids=["286Hz", "100Hz"])
def host(request):
    return simulated_session(7, 30.0, request.param)


def _draws(name, host):
    rng = np.random.default_rng(11)
    return [EFFECTS[name].inject(host, rng) for _ in range(DRAWS)]


def test_accelerometer_bias_injection_above_relevance(host):
    for s, truth in _draws("accelerometer_bias", host):
        d = np.nanmedian(s.acc - host.acc, axis=0)
        assert np.linalg.norm(d) >= acc_bias.RELEVANT_MS2


def test_gyro_bias_drift_injection_above_relevance(host):
    for s, _ in _draws("gyro_bias_drift", host):
        beta = np.rad2deg(s.gyr - host.gyr)
        assert np.max(np.ptp(beta, axis=0)) >= drift.RELEVANT_DEG_S        # peak-to-peak, largest axis


def test_gyro_scale_injection_above_relevance(host):
    for _, truth in _draws("gyro_scale", host):
        M = np.asarray(truth["params"]["scale_matrix"]) - np.eye(3)
        assert np.linalg.norm(M, 2) >= gscale.RELEVANT_SCALE


def test_time_offset_injection_at_least_one_sample_at_any_rate(host):
    """Relevance is one sample period: at 100 Hz the 5 ms lower end of RANGES would be half a sample,
    so the injection's range starts at one period there (`injection_range_s`), and is RANGES at 286 Hz."""
    lo, hi = toff.injection_range_s(host.rate)
    assert lo * host.rate >= 1.0 and hi > lo
    if host.rate > 200.0:
        assert (lo, hi) == (1e-3 * toff.RANGES["tau_ms"][0], 1e-3 * toff.RANGES["tau_ms"][1])
    for _, truth in _draws("time_offset", host):
        assert abs(truth["params"]["tau_s"]) * host.rate >= 1.0
        assert truth["params"]["channel"] in ("acc", "gyr")


def test_vibration_injection_above_relevance(host):
    for s, truth in _draws("vibration", host):
        inside = (s.t >= truth["t_start"] + 1.0) & (s.t <= truth["t_end"] - 1.0)   # past the ramps
        v = (s.acc - host.acc)[inside]
        band_rms = np.sqrt(np.mean(np.sum(v * v, axis=1)))
        assert band_rms >= vib.RELEVANT_RMS


def test_magnetic_disturbance_injection_above_relevance(host):
    for s, truth in _draws("magnetic_disturbance", host):
        inside = (s.t >= truth["t_start"] + 1.0) & (s.t <= truth["t_end"] - 1.0)
        extra = np.nanmedian(np.linalg.norm((s.mag - host.mag)[inside], axis=1))
        field = np.nanmedian(np.linalg.norm(host.mag - np.nanmean(host.mag, axis=0), axis=1))
        assert extra / truth["params"]["field_unit_scale"] >= magnet.RELEVANT_FRACTION
        assert extra / field > 0.5 * magnet.RELEVANT_FRACTION        # same order against the host's own |m|


def test_saturation_injection_above_relevance(host):
    for s, truth in _draws("saturation", host):
        c = truth["params"]["channel"]
        on_rail = np.abs(np.abs(getattr(s, c)) - truth["params"]["level"]) <= 1e-9 * truth["params"]["level"]
        assert int(on_rail.sum()) >= sat.MIN_CLIPPED


def test_linear_acceleration_injection_above_the_largest_ordinary_level(host):
    for s, _ in _draws("linear_acceleration", host):
        a = s.acc - host.acc
        assert np.sqrt(np.mean(np.sum(a * a, axis=1))) >= STANDARD_G     # (L2)'s ceiling is g
