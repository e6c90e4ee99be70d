"""The field-perturbation process (σ_d per nav axis, τ_d) chosen per recording by a held-out predictive score
(Options.field_select; issue 2c, helper G5).

The nav-frame field is n + d_k with d_k a Gauss–Markov process (imugraph.factors.field). How much it may wander
(σ_d) and how fast (τ_d) differs between rooms and paths, and the magnetometer alone cannot tell a slowly
wandering field from a slowly drifting heading. Instead of an EM step (whose fixed point, with the orientations
held, did not settle: options.py "Tried and removed"), each candidate process is scored by how well the
smoother, run WITHOUT the magnetometer samples of some blocks, predicts those samples (K-fold cross-validation
over time blocks):

    fold f holds out the samples of the blocks b with b mod F = f (blocks of block_s seconds);
    e_i = nRb_i · D⁻¹ (y_i − o) − (n + d_k(i))       held-out sample i, unit field (the model's residual)
    score(c) = (1/|H|) Σ_{i ∈ H} min(‖e_i‖², c_huber²)                  over all folds' held-out samples H

In a held-out block the orientation comes from the gyro (and accelerometer) through the neighbouring blocks and
d_k from the process prior between them, so the score rewards a process (and a gyro model) that predicts
data it has not seen — it cannot be won by following the data more closely. The optical truth is not used.
Samples inside detected disturbance windows are left out of the score (their offsets are fitted per window).
The candidate with the lowest score is then run on all the data — when it beats the configured process
significantly over the held-out blocks (paired z ≥ Options.field_select_z, `choose`); otherwise the configured
process is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from imugraph.calibration.result import n_mag_from_dip
from imugraph.folds import held_out_masks, time_blocks
from imugraph.geometry import quat_to_rotmat
from imugraph.io.session import Session

HUBER_CLIP = 0.2     # |e| clipped at 0.2 of the unit field (≈ 11°) in the score: a sample in an undetected
#                      disturbance must not decide the choice alone


@dataclass(frozen=True)
class Candidate:
    """One field process to score: σ_d (per nav axis) and τ_d as multiples of Options.field_sigma/field_tau."""

    sigma_scale: tuple = (1.0, 1.0, 1.0)
    tau_scale: float = 1.0
    gyro_map: bool | None = None          # None: the options' setting

    def apply(self, options):
        """Options with this candidate's field process (and gyro map)."""
        sig = np.broadcast_to(np.asarray(options.field_sigma, float), (3,)) * np.asarray(self.sigma_scale, float)
        out = replace(options, field_sigma=tuple(float(s) for s in sig), field_tau=float(options.field_tau) *
                      self.tau_scale, field_select=False)
        return out if self.gyro_map is None else replace(out, gyro_map=self.gyro_map)

    def label(self) -> str:
        gm = "" if self.gyro_map is None else f" map={self.gyro_map}"
        return f"σ×{tuple(self.sigma_scale)} τ×{self.tau_scale}{gm}"


# The default grid: the configured process, twice as loose across the field, three times slower, both
DEFAULT_CANDIDATES = (Candidate(), Candidate((1.0, 2.0, 1.0)), Candidate(tau_scale=3.0),
                      Candidate((1.0, 2.0, 1.0), 3.0))


def fold_masks(t: np.ndarray, block_s: float, folds: int) -> list[np.ndarray]:
    """(N,) bool per fold: True where that fold holds the magnetometer sample out (blocks of block_s s,
    block b in fold b mod folds)."""
    if folds < 2 or block_s <= 0:
        raise ValueError(f"field_select: found folds={folds}, block_s={block_s}; expected folds ≥ 2, block_s > 0")
    return held_out_masks(t, block_s, folds)


def held_out_errors(session: Session, est, held: np.ndarray, return_index: bool = False):
    """(M, 3) unit-field prediction errors e_i (module docstring) at the held-out samples with a magnetometer
    sample, outside the disturbance windows of `est` (an ml.Estimate from the session without those samples);
    with return_index also their (M,) sample indices."""
    from imugraph.calibration.alignment import undelay_magnetometer

    cal, info = est.calibration, est.info
    y = session.mag
    if cal.mag_delay_s:
        y = undelay_magnetometer(session.t, y, cal.mag_delay_s)        # as calibrate pairs them
    use = held & np.all(np.isfinite(y), axis=1)
    for w in info.get("disturbance_windows", []):
        use &= ~((session.t >= w["t_start"]) & (session.t <= w["t_end"]))
    idx = np.flatnonzero(use)
    if len(idx) == 0:
        return (np.zeros((0, 3)), idx) if return_index else np.zeros((0, 3))
    m_b = np.linalg.solve(cal.D, (y[idx] - cal.o).T).T                 # D⁻¹(y − o): body-frame unit field
    nRb = quat_to_rotmat(est.quat[idx])
    n_pred = np.broadcast_to(n_mag_from_dip(np.deg2rad(cal.dip_deg)), (len(idx), 3))
    d = info.get("field_offsets")
    if d is not None:                    # the sample's keyframe perturbation, as the magnetometer factor uses it
        kf = np.asarray(info["keyframe_samples"])
        k = np.clip(np.searchsorted(kf, idx, side="right") - 1, 0, len(d) - 1)
        n_pred = n_pred + d[k]
    e = np.einsum("nij,nj->ni", nRb, m_b) - n_pred
    return (e, idx) if return_index else e


def score(errors: np.ndarray) -> float:
    """Mean clipped squared error (module docstring); NaN with no held-out sample."""
    if len(errors) == 0:
        return float("nan")
    return float(np.mean(np.minimum(np.sum(errors**2, axis=1), HUBER_CLIP**2)))


def select(session: Session, options, candidates=DEFAULT_CANDIDATES, block_s: float | None = None,
           folds: int | None = None, initial=None, allow_weak: bool = False, z_min: float | None = None):
    """Score each candidate by K-fold held-out prediction of the magnetometer; return (chosen Candidate,
    [{candidate, score, folds, blocks, z}], initial). The chosen one is the lowest score when it beats the
    first candidate (the configured process) by z ≥ z_min over the blocks (`choose`), else the first. The initial calibration (ellipsoid, alignment, noise from rest) is computed
    once from all the data and shared by every fold run (it only starts the graph); when D, o are not
    identifiable each run takes the weak path itself."""
    from imugraph.calibration import ml
    from imugraph.errors import CalibrationError

    block_s = options.field_select_block_s if block_s is None else block_s
    folds = options.field_select_folds if folds is None else folds
    z_min = options.field_select_z if z_min is None else z_min
    if initial is None:
        from imugraph.calibration.initial import initial_calibration
        try:
            initial = initial_calibration(session)
        except CalibrationError:
            if not allow_weak:
                raise
            initial = None       # weak path: each run takes it itself (calibrate then sets the tight θ prior)
    masks = fold_masks(session.t, block_s, folds)
    block = time_blocks(session.t, block_s)
    table = []
    for cand in candidates:
        opt_c = cand.apply(options)
        sq = np.full(session.n, np.nan)         # clipped squared error of each held-out sample
        per_fold = []
        for held in masks:
            mag = session.mag.copy()
            mag[held] = np.nan
            est = ml.calibrate(session.with_mag(mag), opt_c, initial=initial, allow_weak=True)
            e, idx = held_out_errors(session, est, held, return_index=True)
            sq[idx] = np.minimum(np.sum(e**2, axis=1), HUBER_CLIP**2)
            per_fold.append(score(e))
        table.append({"candidate": cand, "score": float(np.nanmean(sq)) if np.isfinite(sq).any() else np.nan,
                      "folds": per_fold, "blocks": block_means(sq, block)})
    return choose(table, candidates[0], z_min), table, initial


def block_means(sq: np.ndarray, block: np.ndarray) -> np.ndarray:
    """(B,) mean clipped squared error of each time block (NaN: no held-out sample in it)."""
    ok = np.isfinite(sq)
    n_b = int(block.max()) + 1
    total = np.bincount(block[ok], sq[ok], n_b)
    count = np.bincount(block[ok], minlength=n_b)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def choose(table: list, reference, z_min: float):
    """The lowest-score candidate if it beats `reference` significantly, else `reference`.

    Paired over the time blocks b (each held out once): Δ_b = s_b(best) − s_b(ref), z = −mean(Δ) / (std(Δ)/√B);
    the best is taken when z ≥ z_min. The blocks are the units, so a difference carried by a few blocks (an
    undetected disturbance, clipped samples) does not count as evidence (BROAD 32: scores 0.03 % apart)."""
    finite = [r for r in table if np.isfinite(r["score"])]
    ref = next((r for r in table if r["candidate"] == reference), None)
    if not finite or ref is None:
        return reference
    best = min(finite, key=lambda r: r["score"])
    for r in table:
        r["z"] = _paired_z(r["blocks"], ref["blocks"])
    return best["candidate"] if best is not ref and best["z"] >= z_min else reference


def _paired_z(a: np.ndarray, b: np.ndarray) -> float:
    """z of mean(b − a) over the blocks where both are finite (positive: a lower, i.e. better, than b)."""
    ok = np.isfinite(a) & np.isfinite(b)
    d = b[ok] - a[ok]
    if len(d) < 3:
        return 0.0
    se = float(np.std(d, ddof=1)) / np.sqrt(len(d))
    return float(np.mean(d)) / se if se > 0 else 0.0


def calibrate_selected(session: Session, options, initial=None, allow_weak: bool = False):
    """ml.calibrate with the field process chosen by `select` (Options.field_select); the choice and the
    scores are in info["field_select"]."""
    from imugraph.calibration import ml

    best, table, init = select(session, options, initial=initial, allow_weak=allow_weak)
    opt_best = best.apply(options)
    est = ml.calibrate(session, opt_best, initial=init, allow_weak=allow_weak)
    est.info["field_select"] = {"chosen": best.label(), "field_sigma": opt_best.field_sigma,
                                "field_tau": opt_best.field_tau,
                                "scores": [{"candidate": r["candidate"].label(), "score": r["score"],
                                            "folds": r["folds"], "z": r.get("z")} for r in table]}
    return est
