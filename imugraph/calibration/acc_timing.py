"""Which orientation each accelerometer sample is paired with: the accelerometer–gyroscope sample timing.

The graphs integrate the gyro with the strapdown forward rule (imugraph.factors.gyro, Forster eq. 35)

    R_{j+1} = R_j Exp(ω_j Δt)                                                        (1)

and rotate accelerometer row j by R_j. That pairing is exact only when ω_j is the rate over [t_j, t_{j+1})
and a_j the specific force at t_j. For instantaneous samples of both, R_j of (1) is the orientation about
½ sample earlier (the left-point rule lags); for a gyro whose row j is the mean rate over [t_{j−1}, t_j]
(integrating/decimating outputs) it is one sample earlier; filters with different group delays on the two
sensors add their difference. VQF integrates the gyro row before using the accelerometer of the same row
(the backward rule): in these terms, a lead of one sample.

A timing error δ (samples, Δt each) turns the gravity the accelerometer sees into a nav-frame horizontal
specific force that does not average out while the sensor turns about a horizontal axis:

    R_j a_{j+δ} − R_{j+δ} a_{j+δ} ≈ −[R_j ω_j]× (g e_z) δΔt = g δΔt (e_z × n_ω)         (2)

(g δΔt |ω| = 0.24 m/s² ≈ 1.4° of tilt at 7 rad/s and δΔt = 3.5 ms). The velocity chain
(imugraph.factors.velocity) integrates it into a drift proportional to the net nav-frame rotation ∫ n_ω dt
(BROAD 30: 275 rad about a horizontal axis), which it can only answer with a tilt about that axis.

δ is a setting of the sensor, `Options.acc_lead_samples`, not an estimate. Estimated jointly (a constant
extra state of the velocity chain, Δv_k − δ Σ_j ΔR_kj (a_{j+1} − a_j) to first order) it recovers a
simulated one-sample lead as 0.95, but on BROAD it returned −0.3 … 0 on the spinning trials 28/30, −1.7 on
36 and +5 on 01: while the sensor spins, the gyro's rate error κ|ω| leaves the tilt about the spin axis free
to absorb most of (2).
`benchmarks/c1_timing.py` measures the accelerometer's timing against the optical reference instead:
δ ≈ 0.5–1 on BROAD's rotation trials.
"""

from __future__ import annotations

import numpy as np

from imugraph.errors import SessionError
from imugraph.geometry import expmap
from imugraph.io.session import Session


def lead_accelerometer(b_acc: np.ndarray, lead_samples: float, b_gyr: np.ndarray | None = None,
                       dt: np.ndarray | None = None, source: str = "<memory>") -> np.ndarray:
    """Accelerometer rows re-timed so that row i holds the specific force at the time of row i's orientation.

    The accelerometer leads the strapdown orientation by δ = lead_samples: row j was sensed at the time of
    orientation j + δ. The whole part n = ⌊δ⌋ moves rows (row i takes row i − n, exact for gravity and
    linear acceleration alike). The fractional part f = δ − n, with the gyro given, rotates the sample back
    by the turn the body made in f·Δt (a body-fixed view of a nav-fixed vector, a_b(t − τ) = Exp(ω τ) a_b(t)):

        a_i ← Exp(f Δt_i ω_i) a_{i−n}                                                      (3)

    which leaves the noise untouched (linear acceleration is re-timed by n only; f < 1 sample of it is
    nothing once integrated to velocity). Without the gyro the fractional part interpolates linearly,
    a_i ← (1 − f) a_{i−n} + f a_{i−n−1} (that averages neighbouring noise). Rows that would come from
    before the first / after the last row repeat it (the sensor at rest there in a recording).

    Args:
        b_acc: (N, 3) m/s², every row a sample (finite).
        lead_samples: δ, samples (> 0: the accelerometer leads; < 0: it lags).
        b_gyr: (N, 3) rad/s (optional, see above); dt: (N,) s, step from row i to i + 1 (with b_gyr).
        source: file name for the error message.

    Returns:
        (N, 3) float array (a new array; the input is not modified).

    Raises:
        SessionError: b_acc or b_gyr not (N, 3), or δ not finite or beyond ±N/2 rows.
    """
    a = np.asarray(b_acc, float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise SessionError(source, "acc", f"shape {a.shape}", "(N, 3)")
    n = a.shape[0]
    d = float(lead_samples)
    if not np.isfinite(d) or abs(d) > max(n // 2, 1):
        raise SessionError(source, "acc_lead_samples", repr(lead_samples),
                           f"a finite number of samples within ±{max(n // 2, 1)}")
    if d == 0.0 or n == 0:
        return a.copy()
    whole = int(np.floor(d))
    f = d - whole
    rows = np.clip(np.arange(n) - whole, 0, n - 1)
    if b_gyr is None:
        nxt = np.clip(rows - 1, 0, n - 1)
        return (1.0 - f) * a[rows] + f * a[nxt]
    w = np.asarray(b_gyr, float)
    if w.shape != a.shape:
        raise SessionError(source, "gyr", f"shape {w.shape}", f"{a.shape}, the accelerometer's")
    step = np.asarray(dt, float) if dt is not None else np.full(n, 0.0)
    return turn_back(a[rows], w, step, f)


def turn_back(b_acc: np.ndarray, b_gyr: np.ndarray, dt: np.ndarray, frac: float) -> np.ndarray:
    """The fractional part of eq. (3): a_i ← Exp(f Δt_i ω_i) a_i, (N, 3) → (N, 3) (a copy when f = 0)."""
    if frac <= 0.0:
        return np.array(b_acc, float)
    return np.einsum("nij,nj->ni", expmap(frac * np.asarray(dt, float)[:, None] * b_gyr), b_acc)


DEFAULT_LEAD = 0.5   # instantaneous gyro and accelerometer samples under the forward rule (1)


def session_lead(session: Session) -> float:
    """δ for a session whose timing is not set by the user: `meta["acc_lead_samples"]` where the source
    states it (imugraph.sim.sensors records 0: its rate is held over [t_j, t_{j+1}), rule (1) exactly),
    else DEFAULT_LEAD."""
    return float(session.meta.get("acc_lead_samples", DEFAULT_LEAD))


def with_lead(session: Session, lead_samples: float) -> Session:
    """A copy of `session` with its accelerometer re-timed by `lead_accelerometer` (with its gyro, eq. 3;
    the other channels unchanged)."""
    if not lead_samples:
        return session
    acc = lead_accelerometer(session.acc, lead_samples, session.gyr, session.dt, session.source)
    return Session(session.t, session.gyr, acc, session.mag, session.quat, session.movement,
                   session.source, session.name, dict(session.meta))
