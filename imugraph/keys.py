"""GTSAM keys used by imugraph graphs, defined in one place (never bare integers).

R(k)  orientation nRb of keyframe k (Rot3)
B(0)  gyroscope bias δ_ω (Vector3, rad/s)
D(0)  magnetometer distortion matrix D as a 9-vector, row-major (Vector)
O(0)  magnetometer offset o (Vector3)
M(0)  field dip δ (Vector1, rad): n_mag = [cos δ, 0, -sin δ]
"""

from gtsam.symbol_shorthand import B, D, M, O, R  # noqa: F401

BIAS = B(0)
DMAT = D(0)
OFFSET = O(0)
DIP = M(0)
