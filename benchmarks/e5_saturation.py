"""Task E (session 16): what the saturation model leaves on a clipped gyro (harness seed 1 case 012:
BROAD 06 clipped at 12.2 rad/s, 3.7 % of samples). The injected session's host is the unclipped truth
(used here to MEASURE the reconstruction, never inside the estimator): the quadratic peak reconstruction's
error at the rail samples, and the whitened gyro residual of the base fit and of the effect's correction,
split into rail samples, their ±0.5 s support, and the rest.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/e5_saturation.py --seed 1 --cases 012
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.e5_hosts import harness_hosts  # noqa: E402
from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects import saturation as sat
from imugraph.diagnose.fit import base_options, fit_base
from imugraph.diagnose.effects.base import replace_session
from imugraph.diagnose.fit import fit_simulation
from imugraph.diagnose.harness import draw_cases, hide_label
from imugraph.diagnose.refit import refit_effect, rescale


def main() -> None:
    a, sessions = harness_hosts(__doc__, "012")

    def fn(s, host):
        cid = s.name.split("_")[-1]
        real = fit_base(s, base_options(5.0))
        corr = sat.EFFECT.fit(real, np.ones(real.n, bool))
        rails = corr.deltas["rails"]["gyr"]
        rec = sat.reconstruct_peaks(s.t, s.gyr, rails)
        hit = np.zeros(s.n, bool)
        for ax, _sg, lv in rails:
            hit |= sat.on_rail(s.gyr[:, ax], lv)
        sup = corr.deltas["support"]
        err_clip = (s.gyr - host.gyr)[hit]
        err_rec = (rec - host.gyr)[hit]
        print(f"{cid}: rails {[(ax, round(lv, 2)) for ax, _s, lv in rails]}, rail samples {hit.sum()}, "
              f"support {sup.mean():.3f}")
        print(f"  at the rail: |clipped − truth| RMS {np.sqrt(np.nanmean(err_clip ** 2)):.3f} rad/s, "
              f"|quadratic − truth| RMS {np.sqrt(np.nanmean(err_rec ** 2)):.3f} rad/s, "
              f"mean signed (rec − truth) {np.nanmean(err_rec):+.3f}")
        sig = np.asarray(real.sigma["gyr"], float)
        after = corr.raw_residuals(real)["gyr"]
        for lab, m in (("rail", hit), ("support∖rail", sup & ~hit), ("outside", ~sup)):
            zb = real.residuals["gyr"][m] / sig
            za = after[m] / sig
            print(f"  {lab:13s} whitened gyro residual RMS: base {np.sqrt(np.nanmean(zb ** 2)):.2f}, "
                  f"corrected {np.sqrt(np.nanmean(za ** 2)):.2f}  (n {m.sum()})")
        ext, info = refit_effect(sat.EFFECT, real, 2, None)
        all_ = np.ones(real.n, bool)
        ref = rescale(sat.EFFECT.fit(ext, all_).raw_residuals(ext), real, all_)["gyr"]
        recon = fit_simulation(replace_session(s, gyr=rec), real)   # base model refitted to the reconstruction
        hf = fit_base(host, base_options(5.0))
        for lab, m in (("rail", hit), ("support∖rail", sup & ~hit), ("outside", ~sup)):
            zr = ref[m] / sig
            zc = recon.residuals["gyr"][m] / np.asarray(recon.sigma["gyr"], float)
            zh = hf.residuals["gyr"][m] / np.asarray(hf.sigma["gyr"], float)
            print(f"  {lab:13s} refit (F1) RMS {np.sqrt(np.nanmean(zr ** 2)):.2f}, one fit to the reconstruction "
                  f"{np.sqrt(np.nanmean(zc ** 2)):.2f}, host (unclipped) base fit {np.sqrt(np.nanmean(zh ** 2)):.2f}")
        from imugraph.factors.gyro import keyframe_layout
        kf, _ = keyframe_layout(real.n, int(real.info["stride"]), s.dt)     # as the fit's layout (gaps)
        k_of = np.searchsorted(kf, np.arange(real.n), side="right") - 1
        in_iv = np.isin(k_of, np.unique(k_of[hit]))                     # keyframe intervals holding a rail sample
        for lab, m in (("interval∖rail", in_iv & ~hit), ("support∖interval", sup & ~in_iv)):
            zr = ref[m] / sig
            zh = hf.residuals["gyr"][m] / np.asarray(hf.sigma["gyr"], float)
            print(f"  {lab:16s} refit (F1) RMS {np.sqrt(np.nanmean(zr ** 2)):.2f}, host {np.sqrt(np.nanmean(zh ** 2)):.2f} "
                  f"(n {m.sum()})")
        print(f"  σ_gyr base {np.round(sig, 4)}, host {np.round(np.asarray(hf.sigma['gyr'], float), 4)}, "
              f"refit {np.round(np.asarray(ext.sigma['gyr'], float), 4)}")

    keep = {c.zfill(3) for c in a.cases.split(",")}      # the harness' cases, drawn once (host, then injection)
    for cid, host, injected, _name, _truth in draw_cases(sessions, list(EFFECTS), 2, np.random.default_rng(a.seed)):
        if cid in keep:
            fn(hide_label(injected, cid), host)


if __name__ == "__main__":
    main()
