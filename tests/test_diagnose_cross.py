"""S16 (issue 5): the gap's cross-channel term (G1')/(G4) — the correlation of the acc and mag residuals with
the model's motion derivative ḣ = h × ω̂ (imugraph/diagnose/gap.py). Known answers, ≈ 0 on data from the
model, and it sees a channel delay that (G1) barely sees. Simulated sessions (30 s at 100 Hz)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from imugraph.diagnose import gap as G
from imugraph.diagnose.attribute import AttributionOptions
from imugraph.diagnose.fit import fit_base, fit_simulation, simulate_from_fit
from imugraph.io.session import Session
from imugraph.sim.motion import random_rotation_motion
from imugraph.sim.sensors import SensorParams, simulate_imu

PARAMS = SensorParams(gyro_bias=[0.01, -0.02, 0.005], gyro_noise=0.005, acc_noise=0.05, mag_noise=0.01,
                      mag_D=np.diag([1.1, 0.9, 1.0]), mag_o=[0.2, -0.1, 0.05])
CROSS = replace(G.GapOptions(), cross_weight=1.0)


def model_session(seed: int, duration: float = 30.0) -> Session:
    rng = np.random.default_rng(seed)
    return simulate_imu(*random_rotation_motion(duration, 100, rng, pauses=2), PARAMS, rng)


def test_motion_correlation_known_answer_and_mask():
    """z = a·u + e (unit-variance u, e independent): correlation a/√(a² + 1) per axis; masked rows ignored."""
    rng = np.random.default_rng(0)
    n = 20000
    u = rng.standard_normal((n, 3))
    a = np.array([0.0, 1.0, -2.0])
    z = a * u + rng.standard_normal((n, 3))
    mask = np.ones(n, bool)
    mask[:100] = False
    z[:100] = 1e6                                            # outside the mask: must not count
    x = G.motion_correlation(z, u, mask)
    np.testing.assert_allclose(x, a / np.sqrt(a**2 + 1), atol=4 / np.sqrt(n))
    assert np.all(G.motion_correlation(z, u, np.zeros(n, bool)) == 0)


def test_covariance_form_known_answer_is_not_diluted_by_independent_misfit():
    """(G4'): z = a·u + k·e, std(u) = 1: the covariance form gives a whatever k (an independent misfit does not
    dilute it), the correlation a/√(a² + k²) falls with k."""
    rng = np.random.default_rng(1)
    n = 20000
    u = 3.0 * rng.standard_normal((n, 3))                     # u's scale must not matter (ũ normalised)
    a = np.array([0.2, -0.5, 0.0])
    mask = np.ones(n, bool)
    for k in (1.0, 4.0):
        z = a * u / 3.0 + k * rng.standard_normal((n, 3))
        np.testing.assert_allclose(G.motion_correlation(z, u, mask, "cov"), a, atol=4 * k / np.sqrt(n))
        np.testing.assert_allclose(G.motion_correlation(z, u, mask), a / np.sqrt(a**2 + k**2),
                                   atol=4 / np.sqrt(n))


def test_cross_term_is_off_by_default():
    assert G.GapOptions().cross_weight == 0.0


@pytest.mark.parametrize("seed,form", [(1, "corr"), (2, "cov")])
def test_gap_with_cross_term_near_zero_when_data_come_from_the_model(seed, form):
    """The existing (G1) test with (G1') added: data from the model stay below the detection floor."""
    opt = replace(CROSS, cross_form=form)
    real = fit_base(model_session(seed))
    rng = np.random.default_rng(100 + seed)
    a = fit_simulation(simulate_from_fit(real, rng), real)
    b = fit_simulation(simulate_from_fit(real, rng), real)
    g = G.gap(real.residuals, a.residuals, real.sigma, real.session.rate, opt=opt, fits=(real, a))
    null = G.gap(b.residuals, a.residuals, real.sigma, real.session.rate, opt=opt, fits=(b, a))
    for c in G.CHANNELS:
        assert g[c] < AttributionOptions().min_gap_ratio * null[c], (c, g[c], null[c])
    for f in (real, a, b):                                    # (G4) itself ≈ 0 ± a few /√N on model data
        z = f.residuals["acc"] / real.sigma["acc"]
        x = G.motion_correlation(z, G.motion_derivatives(f)["acc"], np.ones(f.n, bool), form)
        assert np.all(np.abs(x) < 5 / np.sqrt(f.n)), x


@pytest.mark.parametrize("form", ["corr", "cov"])
def test_cross_term_sees_an_accelerometer_delay(form):
    """acc delayed by 3 samples (30 ms): (G4) of the real residuals is far from the simulation's, so the
    acc gap rises by much more with (G1') than without; the same session undelayed does not."""
    s = model_session(4)
    k = 3
    acc = np.vstack([np.repeat(s.acc[:1], k, axis=0), s.acc[:-k]])           # y(t_j) = h(t_{j−k})
    late = Session(s.t, s.gyr, acc, s.mag, s.quat, s.movement, s.source, "late", dict(s.meta))
    rises = {}
    for name, sess in (("clean", s), ("late", late)):
        real = fit_base(sess)
        sim = fit_simulation(simulate_from_fit(real, np.random.default_rng(7)), real)
        g0 = G.gap(real.residuals, sim.residuals, real.sigma, real.session.rate)["acc"]
        g1 = G.gap(real.residuals, sim.residuals, real.sigma, real.session.rate, opt=replace(CROSS, cross_form=form),
                   fits=(real, sim))["acc"]
        rises[name] = g1 - g0
    assert rises["late"] > 0.3, rises
    assert rises["clean"] < 0.05, rises
