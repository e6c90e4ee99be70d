"""Windowed hard-iron offsets in the stream (θ as a graph state), and which state is "normal": the batch's semantics
of `imugraph.calibration.disturbance`, causally.

The batch models a disturbance window w (a magnet or ferrous tool attached to the sensor for a while) by its own
body-frame offset Δo_w (calibration.disturbance, "windowed hard iron"):

    y_j = D bRn_j n + o + Δo_w + e_j,   j ∈ w                                                              (1)

and its "normal" state — the one whose hard iron is reported as o — is the majority of the WHOLE recording: the
initial calibration is fitted to all samples, the windows are what leaves that sphere. The stream with
`disturb_detect` found windows causally but gave their keyframes no information on θ, and its "normal" was the
bootstrap's: on BROAD 32 the magnet is on for 58 s of the bootstrap's 101 s, so the bootstrap's normal is the
magnet, every later keyframe was flagged (1100) and θ kept the magnet's o (240 model std from the batch).

Here (`StreamOptions.disturb_offsets`, with `calib_states` and `disturb_detect`):
- every window of the detector (stream_disturb) gets one 3-vector key Δo_w (`offset_key`), free: a weak prior
  N(0, (OFFSET_PRIOR_REL × scale)²) only; its keyframes' magnetometer factors are (1) on (pose_k, d_k, Δo_w)
  (stream_calstate eq. 1 with o + Δo_w at the pinned θ; ∂e/∂Δo_w = I), so the orientations there see the field
  with the window's own offset instead of a Huber-downweighted misfit. Δo_w starts at the first keyframe's mean
  residual (that factor's residual is then zero: (1) is linear in Δo_w). The key is re-stamped while its window
  is open, and afterwards while it is the largest window so far (the only candidate for the majority); any other
  is marginalised with the lag. The start calibration's own windows keep their handling (field corrected by the
  start's offsets, no θ);
- the window keyframes still give no information on θ. Measured (BROAD, cached bootstraps, max z of D, o against
  the whole-trial batch with the reported std; docs/stream.md "Windowed offsets and the majority"): without θ in
  them 32: 1.58, 34: 1.01, 28: 0.90; with the detector windows informing θ (after MIN_OFFSET_S and while
  explained) 32: 4.90, 34: 3.76; with the start's modelled windows given offsets and θ too 34: 3.20 (filtered
  4.65 → 5.07°);
- "normal" is the majority of what has been seen so far: when the largest window's field samples outnumber those
  of the keyframes outside every window (with θ information), and its offset explains them — RMS of its
  keyframes' whitened residuals at the pin ≤ EXPLAINED (3, the batch's) × that of the normal keyframes —, the
  roles swap in what is REPORTED: the streamed calibration's hard iron is o + Δo_w (D, dip unchanged; (1) with
  w the new normal and the old normal a window with offset −Δo_w). Decided at each record on the data seen so
  far; at the end of a trial that is the batch's rule (over the stream's windows). The graph itself is not
  re-parametrised (θ stays pinned at the start, the orientations are unaffected by the decision).

The swapped estimate needs θ and Δo_w jointly: with Ψ = (θ, Δo_w), J iSAM2's joint marginal information of Ψ
(`jointMarginalInformation`: the orientations profiled out), H = J − diag(Λ_p, 0) the data's part and W = diag(Λ_w, 0)
the weak prior on θ about θ₀ (Δo_w's own prior is in the graph), the minimum of the data's quadratic plus W is

    Ψ_s = Ψ̂ + (H + W)⁻¹ [(Λ_p − Λ_w)(θ̂ − θ₀) + Λ_w (c − θ₀); 0],   cov Ψ_s = (H + W)⁻¹                   (2)

(stream_calstate eq. 3–4 for θ alone; c the weak prior's centre, θ₀ by default); the reported o = o_s + Δo_s with
cov A cov Aᵀ (A adds the Δo rows to the o rows).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from imugraph.calibration.disturbance import EXPLAINED
from imugraph.factors.theta import THETA_DIM

__all__ = ["OFFSET_PRIOR_REL", "WindowOffsets", "joint_estimate", "offset_key", "swap_hard_iron"]

OFFSET_PRIOR_REL = 2.0      # σ of Δo_w's prior, relative to the field scale (a magnet: BROAD 32, 1.3 × the field)
O_SLICE = slice(9, 12)      # o inside θ (factors.theta: vec D, o, δ)


def offset_key(i: int) -> int:
    """Key of the i-th disturbance window's offset Δo_w (a Vector3, raw field units)."""
    return gtsam.symbol("w", int(i))


def joint_estimate(psi_hat: np.ndarray, J: np.ndarray, theta0: np.ndarray, pin_sig: np.ndarray, weak_sig: np.ndarray,
                   prior_mean: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (2): Ψ_s and its covariance from the pinned solver's estimate Ψ̂ = (θ̂, rest) and joint marginal
    information J (θ first, THETA_DIM rows)."""
    n = THETA_DIM
    J = 0.5 * (np.asarray(J, float) + np.asarray(J, float).T)
    lam_p = 1.0 / np.asarray(pin_sig, float) ** 2
    lam_w = 1.0 / np.asarray(weak_sig, float) ** 2
    A = J.copy()
    A[:n, :n] += np.diag(lam_w - lam_p)                     # H + W
    d = np.asarray(psi_hat[:n], float) - theta0
    rhs = np.zeros(len(J))
    rhs[:n] = (lam_p - lam_w) * d
    if prior_mean is not None:
        rhs[:n] += lam_w * (np.asarray(prior_mean, float) - theta0)
    cov = np.linalg.inv(A)
    return np.asarray(psi_hat, float) + cov @ rhs, 0.5 * (cov + cov.T)


def swap_hard_iron(psi: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """θ (13,) with o + Δo_w as its hard iron, and its covariance, from Ψ = (θ, Δo_w) and cov Ψ (16×16)."""
    n = THETA_DIM
    A = np.zeros((n, n + 3))
    A[:, :n] = np.eye(n)
    A[O_SLICE, n:] = np.eye(3)
    return A @ psi, A @ cov @ A.T


class WindowOffsets:
    """Book-keeping of the windows' offset keys, sample counts and residuals (constant size per window).

    Window ids are hashable labels from the caller (("start", i) for the start calibration's windows, ("detector",
    j) for the detector's). `scale`: the field scale (for the prior)."""

    def __init__(self, scale: float):
        self.scale = float(scale)
        self.index: dict = {}       # window id → i (offset_key(i))
        self.lin: dict = {}         # i → Δo_w at which its latest factor was linearised (the latest estimate)
        self.samples: dict = {}     # i → valid field samples in its keyframes
        self.r2: dict = {}          # i → [Σ |r_pin|², keyframes] (whitened residual at the pin)
        self.normal_samples, self.normal_r2 = 0, [0.0, 0]
        self.largest = None         # i of the window with the most samples

    def key_of(self, wid, estimate) -> tuple[int, np.ndarray | None]:
        """(key, Δo_w to linearise at: the solver's latest estimate, `estimate(key)` → (3,) or None; None for a
        new window — it starts at the first keyframe's residual)."""
        i = self.index.get(wid)
        if i is None:
            return offset_key(len(self.index)), None
        v = estimate(offset_key(i))
        return offset_key(i), self.lin[i] if v is None else np.asarray(v, float)

    def added(self, wid, offset: np.ndarray, n: int, r2: float, graph, values, stamps, now: float) -> None:
        """Keyframe of window `wid` added with its factor linearised at `offset`; a new window's key (value, prior
        N(0, (OFFSET_PRIOR_REL × scale)²))."""
        i = self.index.get(wid)
        if i is None:
            i = self.index[wid] = len(self.index)
            values.insert(offset_key(i), np.asarray(offset, float))
            graph.add(gtsam.PriorFactorVector(offset_key(i), np.zeros(3),
                                              gtsam.noiseModel.Isotropic.Sigma(3, OFFSET_PRIOR_REL * self.scale)))
            self.samples[i], self.r2[i] = 0, [0.0, 0]
        self.lin[i] = np.asarray(offset, float)
        self.samples[i] += int(n)
        self.r2[i][0] += float(r2)
        self.r2[i][1] += 1
        if self.largest is None or self.samples[i] > self.samples[self.largest]:
            self.largest = i
        stamps[offset_key(i)] = now

    def normal(self, n: int, r2: float) -> None:
        """A keyframe outside every window, with information on θ."""
        self.normal_samples += int(n)
        self.normal_r2[0] += float(r2)
        self.normal_r2[1] += 1

    def keep(self, alive) -> tuple:
        """Keys to re-stamp (the largest window's, while it is in the solver: `alive(key)`)."""
        if self.largest is None:
            return ()
        key = offset_key(self.largest)
        return (key,) if alive(key) else ()

    def explained(self, i: int) -> bool:
        """Window i's residual RMS within EXPLAINED × the normal keyframes' (calibration.disturbance's rule)."""
        s, n = self.r2[i]
        s0, n0 = self.normal_r2
        if not n or not n0:
            return False
        return math.sqrt(s / n) <= EXPLAINED * math.sqrt(s0 / n0)

    def majority(self, alive) -> int | None:
        """The window that is the normal state now (its samples outnumber the normal keyframes' and its offset
        explains them; its key still in the solver), else None."""
        i = self.largest
        if i is None or self.samples[i] <= self.normal_samples or not self.explained(i) or not alive(offset_key(i)):
            return None
        return i

    def row(self, major: int | None) -> dict:
        """History-row fields: which window is the normal state (None: the start's), the windows with an offset,
        the normal keyframes' and the largest window's field samples."""
        return {"normal_window": major, "offset_windows": len(self.index), "normal_samples": self.normal_samples,
                "largest_window_samples": 0 if self.largest is None else self.samples[self.largest]}
