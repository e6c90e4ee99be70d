"""imugraph: IMU sensor fusion with factor graphs on GTSAM.

Magnetometer calibration in combination with inertial sensors (Kok & Schön), batch orientation
smoothing, and the tools around them (readers, simulator, evaluation).
"""

__version__ = "0.1.0"
