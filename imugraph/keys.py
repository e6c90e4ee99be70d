"""GTSAM keys used by imugraph graphs, defined in one place (never bare integers).

R(k)  orientation nRb of keyframe k (Rot3)
V(k)  velocity of keyframe k in the navigation frame (Vector3, m/s), when linear acceleration is modelled
B(i)  gyroscope bias δ_ω of bias segment i (Vector3, rad/s); a random walk joins consecutive segments
C(0)  magnetometer calibration θ = (vec D row-major (9), o (3), dip δ (1)) as one Vector13.
      One vector key keeps every magnetometer factor a two-key (R_k, θ) factor, which the batch solver
      turns into one HessianFactor per keyframe, and gives the marginal covariance of D, o, δ in one block.
"""

from gtsam.symbol_shorthand import B, C, R, V  # noqa: F401

BIAS = B(0)
CALIB = C(0)


def rot(k: int) -> int:
    """Key of keyframe k's orientation."""
    return R(int(k))


def bias(i: int) -> int:
    """Key of the gyro bias of bias segment i."""
    return B(int(i))


def vel(k: int) -> int:
    """Key of keyframe k's velocity."""
    return V(int(k))
