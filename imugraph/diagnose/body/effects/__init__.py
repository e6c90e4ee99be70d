"""Effect library of the body diagnosis: one module per effect (soft_tissue, gyro_bias_drift,
accelerometer_bias), interface in imugraph.diagnose.body.effects.base."""
