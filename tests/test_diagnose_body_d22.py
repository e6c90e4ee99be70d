"""Session 22 (helper D22) options of the body diagnosis: the chunked warm start of the base fit
(imugraph.diagnose.body.chunked) and soft_tissue over a fitted window (effects/soft_tissue_window.py).
Sessions: the analytic lower-body walk of tests/test_diagnose_body.py."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_diagnose_body import _session  # noqa: E402

from imugraph.diagnose.body.chunked import chunk_bounds  # noqa: E402
from imugraph.diagnose.body.effects.soft_tissue import EFFECT as SOFT  # noqa: E402
from imugraph.diagnose.body.effects.soft_tissue_window import EFFECT as SOFT_W, windows  # noqa: E402
from imugraph.diagnose.body.fit import fit_body  # noqa: E402


def test_chunk_bounds_cover_every_keyframe_with_the_overlap():
    kf_t = np.arange(0.0, 61.0, 0.1)
    b = chunk_bounds(kf_t, 10.0, 2.0)
    assert b[0][0] == 0 and b[-1][1] == kf_t.size - 1
    for (a0, b0), (a1, b1) in zip(b[:-1], b[1:]):
        assert a0 < a1 <= b0 < b1                                   # overlapping, moving forward
        assert abs((kf_t[b0] - kf_t[a1]) - 2.0) < 0.11              # (C1) 2 s overlap
    assert all(kf_t[bb] - kf_t[aa] <= 15.0 + 1e-9 for aa, bb in b)  # a short tail joins the last chunk


def test_windows_start_with_the_whole_recording_and_respect_the_minimum():
    W = windows(10, 1.0, 2.0)
    assert tuple(W[0]) == (0, 10)
    assert np.all(W[:, 1] - W[:, 0] >= 2) and len({tuple(w) for w in W}) == len(W)
    assert len(W) == 1 + sum(1 for i in range(10) for j in range(i + 2, 11)) - 1


def test_chunked_start_reaches_the_cold_fits_optimum():
    s = _session(16.0, seed=1)
    cold = fit_body(s)
    warm = fit_body(s, chunk_s=5.0)
    assert len(warm.info["chunk_iterations"]) >= 3
    c0, c1 = cold.info["cost_final"], warm.info["cost_final"]
    assert abs(c1 - c0) <= 0.01 * c0, (c0, c1)
    R0 = cold.sensors["LeftLowerLeg"].R_kf
    R1 = warm.sensors["LeftLowerLeg"].R_kf
    rel = np.einsum("kba,kbc->kac", R0, R1)
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert np.percentile(ang, 95) < 1.0                               # the same trajectory up to the LM tolerance


def test_windowed_soft_tissue_finds_the_window_of_a_windowed_wobble():
    s = _session(16.0, seed=0)
    inj, truth = SOFT.inject(s, np.random.default_rng(3), sensor="LeftUpperLeg", strength=0.02, window=(9.0, 14.0))
    bfit = fit_body(inj)
    sf = bfit.sensors["LeftUpperLeg"]
    sigma = {c: np.maximum(np.sqrt(np.mean(r**2, axis=0)), 1e-9) if r.shape[1] else np.ones(0)
             for c, r in sf.residuals.items()}
    every = {c: np.ones(r.shape[0], bool) for c, r in sf.residuals.items()}
    whole = SOFT.fit(bfit, "LeftUpperLeg", every, sigma)
    win = SOFT_W.fit(bfit, "LeftUpperLeg", every, sigma)
    assert win.t_start is not None
    inter = max(0.0, min(win.t_end, 14.0) - max(win.t_start, 9.0))
    union = max(win.t_end, 14.0) - min(win.t_start, 9.0)
    assert inter / union >= 0.5, (win.t_start, win.t_end)
    # the size inside the window is the wobble's; the global fit dilutes it over the whole recording
    assert win.size["value"] > whole.size["value"]
    assert 0.3 < win.size["value"] / truth["params"]["translation_rms_m"] < 3.0
