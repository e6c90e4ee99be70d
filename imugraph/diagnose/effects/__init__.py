"""The effect library of the diagnosis: one module per effect the base model leaves out (DESIGN.md names).

`EFFECTS[name]` is an `Effect` (imugraph.diagnose.effects.base): `inject(session, rng)` adds the effect to a
session with randomised, physically realistic parameters (each module documents its ranges) and returns
the truth; `fit(fit, train)` extends a base `Fit` with the effect, estimated on the training samples, and
returns a `Correction` whose `residuals(fit)` evaluates the extended model at every sample.
"""

from __future__ import annotations

from imugraph.diagnose.effects import (accelerometer_bias, gyro_bias_drift, gyro_scale, linear_acceleration,
                                       magnetic_disturbance, saturation, time_offset, timestamp_jitter, vibration)
from imugraph.diagnose.effects.base import Correction, Effect

# timestamp_jitter last (session 20): the harness draws its cases effect by effect from one random stream, so the
# earlier effects' cases stay what they were. run.load_effects drops it when its flag is off.
EFFECTS: dict = {m.EFFECT.name: m.EFFECT for m in (
    magnetic_disturbance, linear_acceleration, gyro_bias_drift, time_offset, gyro_scale, saturation,
    accelerometer_bias, vibration, timestamp_jitter)}

__all__ = ["EFFECTS", "Effect", "Correction"]
