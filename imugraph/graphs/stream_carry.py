"""The lagging magnetometer's fields that arrive after their interval closed, carried into the next keyframe's factor
(`StreamOptions.mag_carry`, off by default; session 22, helper F22a — the "Also" of U22's acceptance run).

A magnetometer that lags the gyro by s₀ = round(mag_delay_s · rate) samples reports, with row r of the stream, the field
the body saw at row r − s₀ (`stream_interval.ArrivalMixin._attach_delayed_mag`). The first s₀ fields of interval k therefore
belong to the last s₀ rows of interval k − 1, which closed (its factors built) when interval k's first row arrived.
Without this option they are dropped (`counts.mag_dropped`: s₀/stride of the field samples; 10 % on BROAD at 286 Hz, 30 %
— 813 of 2669 distinct readings, not held duplicates — on fusion/sensor_data.csv's ≈ 20 Hz field at 99 Hz, s₀ = 3).

With it, interval k's magnetometer factor (one averaged field on keyframe k, `_mag_factor`) takes those rows too, each
rotated into keyframe k through the closed interval's own preintegrated rotations (no new state, no added latency):

    ᵏR_b(j) = ΔR_{k−1}ᵀ · ᵏ⁻¹R_b(j),   j one of interval k − 1's last s₀ rows                          (C1)

(ΔR_{k−1} = ᵏ⁻¹R_k, interval k − 1's rotation; ᵏ⁻¹R_b(j) its row j's rotation, both from `interval_preintegration`). The
start disturbance windows are applied at the rows' own times. With keep_history under full iSAM2 the rows are also
written into interval k − 1's kept rows (`_hist_y`, `_hist_raw`), so the end graph's exact re-issue pairs each with its
own keyframe, as the batch does (each field sample in exactly one factor there too). Rows whose target lies before
interval k − 1 (an interval shorter than s₀ after a gap) stay dropped.
"""

from __future__ import annotations

import math

import numpy as np


class MagCarryMixin:
    """`_with_carry`, `_carry_rows` and `_keep_tail` of StreamSmoother (state: `_tail`, `_head_mag`; options.mag_carry)."""

    def _keep_tail(self, t: np.ndarray, kRb: np.ndarray, delta_R: np.ndarray, k: int) -> None:
        """After interval k closed: its last s₀ rows' times and rotations ᵏR_b(j), and ΔR_k, for eq. (C1)."""
        if not (self.opt.mag_carry and self._mag_shift > 0):
            return
        s, n = self._mag_shift, len(kRb)
        self._tail = (np.asarray(t[max(0, n - s):n], float), np.asarray(kRb[max(0, n - s):n], float),
                      np.asarray(delta_R, float), k, n)

    def _with_carry(self, k: int, kRb: np.ndarray, y: np.ndarray) -> tuple:
        """Interval k's magnetometer-factor rows (kRb, y) with the carried ones (`_carry_rows`) in front, also written
        into interval k − 1's kept rows (`_carry_history`), and whether there were any; unchanged without."""
        carry = self._carry_rows(k) if self.opt.mag_carry and self._mag_shift > 0 else None
        if carry is None:
            return kRb, y, False
        self._carry_history(k, *carry[1:])
        return np.concatenate([carry[0], kRb]), np.concatenate([carry[1], y]), True

    def _carry_rows(self, k: int):
        """The fields that arrived with the open interval's first s₀ rows (`_head_mag`) and belong to interval k − 1:
        (kRb (c, 3, 3) by eq. (C1), y (c, 3) with the start windows, raw (c, 3), tail row index in interval k − 1 (c,)),
        or None when there are none."""
        tail, head = getattr(self, "_tail", None), getattr(self, "_head_mag", None)
        if tail is None or not head or tail[3] != k - 1:
            return None
        t_tail, kRb_tail, dR, _, n_prev = tail
        s, lost = self._mag_shift, self._mag_shift - len(t_tail)       # head row r → interval k − 1's row n_prev − s + r
        pick = [(r - lost, m) for r, m in enumerate(head[:s]) if r >= lost and math.isfinite(m[0] + m[1] + m[2])]
        if not pick:
            return None
        idx = np.array([j for j, _ in pick])
        raw = np.array([m for _, m in pick], float)
        y, _ = self._start_windowed(t_tail[idx], raw)
        kRb = np.einsum("ji,njk->nik", dR, kRb_tail[idx])                   # (C1): ΔRᵀ · ᵏ⁻¹R_b(j)
        self.stats.mag_dropped -= len(idx)                                    # counted as dropped on arrival
        return kRb, y, raw, n_prev - len(t_tail) + idx

    def _carry_history(self, k: int, y: np.ndarray, raw: np.ndarray, rows: np.ndarray) -> None:
        """Write the carried rows into interval k − 1's kept rows (full iSAM2, keep_history): the end graph pairs them
        with keyframe k − 1, their own."""
        if self.opt.lag_s is None and self.opt.keep_history and len(self._hist_y) == k:
            self._hist_y[k - 1] = np.array(self._hist_y[k - 1], float)
            self._hist_y[k - 1][rows] = y
            hist_raw = getattr(self, "_hist_raw", None)
            if hist_raw is not None and len(hist_raw) == k:
                hist_raw[k - 1] = np.array(hist_raw[k - 1], float)
                hist_raw[k - 1][rows] = raw
