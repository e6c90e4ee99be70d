"""Measurement models, one module each: residual, Jacobians (tested numerically), GTSAM factory.

Each model module exposes a vectorised `*_model(...)` returning residuals and Jacobians for many samples
at once (used by the batch solver) and a `*_factor(...)` factory wrapping the same function in a
`gtsam.CustomFactor` (used by incremental solvers and tests).
"""
