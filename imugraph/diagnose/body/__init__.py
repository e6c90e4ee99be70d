"""Sim-to-real diagnosis of body (multi-IMU) sessions: docs/diagnose_body.md; entry point
`imugraph.diagnose.body.run.diagnose_body`."""
