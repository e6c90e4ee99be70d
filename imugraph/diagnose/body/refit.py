"""Stage 2 of the body attribution: the full refit of a candidate (docs/diagnose_body.md §4).

A large effect bends the base fit (a wobbling thigh sensor pulls its joints, the neighbours' positions and the
pelvis: measured on a simulated walk, the gaps of every sensor of the leg grow), so the first-order fit (BE1)
against the bent trajectory recovers only part of it. As the single-IMU stage 2 (imugraph.diagnose.refit, F1):

    round r = 1, 2:  φ_r = E.fit(θ_{r−1} against the ORIGINAL data, all rows)
                     y_r = y + Δ(φ_r)               (BodyCorrection.deltas: the effect removed from the sensor)
                     θ_r = fit_body(y_r)            (the body graph, defaults, the base fit's N-pose window)

θ* = θ_2 replaces the base fit for that candidate; the cross-validation then repeats against θ* (the effect
fitted per fold from scratch on the ORIGINAL measurements of the sensor, scored on the held-out rows), and
the "before" stays the base fit's. θ* saw the held-out rows through the few global φ (a weak leak, as in the
single-IMU stage 2). Only the effect's sensor is scored.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from imugraph.diagnose.body.effects.base import with_sensor
from imugraph.diagnose.body.fit import BodyFit, fit_body, refit_body_warm, residuals_with
from imugraph.diagnose.body.simulate import fit_options
from imugraph.diagnose.effects.base import replace_session
from imugraph.io.body_session import BodySession

ROUNDS = 2


def corrected_session(session, sensor: str, deltas: dict) -> BodySession:
    """The body session with the effect removed from one sensor (y' = y + Δ); inputs untouched."""
    ses = session.sensors[sensor]
    new = replace_session(ses, gyr=ses.gyr + deltas["gyr"] if "gyr" in deltas else None,
                          acc=ses.acc + deltas["acc"] if "acc" in deltas else None)
    return with_sensor(session, sensor, new, {}, name=session.name)


def against_original(theta: BodyFit, original, sensor: str) -> BodyFit:
    """θ fitted to corrected data, with the sensor's residuals evaluated on its ORIGINAL measurements."""
    sensors = dict(theta.sensors)
    sf = theta.sensors[sensor]
    ses = original.sensors[sensor]
    tmp = BodyFit(original, theta.result, theta.kf, sensors, theta.g, {})
    sensors[sensor] = replace(sf, residuals=residuals_with(tmp, sensor, gyr=ses.gyr, acc=ses.acc))
    return BodyFit(original, theta.result, theta.kf, sensors, theta.g, dict(theta.info, refit_of=sensor))


def refit_effect(effect, real: BodyFit, sensor: str, sigma: dict, opts=None, warm: bool = True,
                 max_iterations: int | None = None) -> BodyFit:
    """θ* (module doc) for one effect on one sensor. warm: each round's body solve reuses the previous
    solution's problem and starts from its values (fit.refit_body_warm: same graph, only the sensor's
    preintegration rebuilt); False: a cold fit from scratch (fit_body), as the recording's. max_iterations:
    LM iterations of each warm round (None: the body options'; session 23: 1 — from the converged previous
    solution the first step takes the cost within 0.05 % of where the default stops, and each further
    iteration costs 1–2 more eliminations of the whole graph: measured on the 3-minute 100 Hz loop)."""
    opts = fit_options(real, opts)
    theta = real
    prev = real
    sf = real.sensors[sensor]
    everything = {c: np.ones(r.shape[0], bool) for c, r in sf.residuals.items()}
    iterations = []
    for _ in range(ROUNDS):
        corr = effect.fit(theta, sensor, everything, sigma)
        session = corrected_session(real.session, sensor, corr.deltas)
        if warm and prev.problem is not None:
            fitted = refit_body_warm(prev, session, sensor, max_iterations)
        else:
            fitted = fit_body(session, opts, lm=real.info.get("lm"))
        prev = fitted
        iterations.append(int(fitted.info.get("iterations", -1)))
        theta = against_original(fitted, real.session, sensor)
    theta.info["rounds_iterations"] = iterations
    return theta
