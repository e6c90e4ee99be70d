"""imugraph.calibration"""
