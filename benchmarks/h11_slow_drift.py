"""H11 (issue 2c): what the slow drift on BROAD 02/06/15/16 is — diagnosis against the optical truth (evaluation only).

    .venv/bin/python benchmarks/h11_slow_drift.py 02,06,15,16 [--opt FIELD=VALUE ...]

Per trial, imugraph's estimate (calibrate, the given Options) and offline VQF's (cached as in h4_decompose),
each at its own best alignment (shift, constant heading), are compared keyframe by keyframe (5 Hz) in imugraph's
nav frame (x along the horizontal field, y across it, z up); "slow" is a moving average over 2 s (as h4_error_split).

Heading and the field (A). With the truth orientation R (ours up to ψ) and imugraph's calibration, the field
the sensor saw in the nav frame is R·D⁻¹(y − o); its deviation from n(δ) = (cos δ, 0, −sin δ) is the field
perturbation the model calls d (factors/field.py):  d_true = R·D⁻¹(y − o) − n(δ)  (averaged per keyframe).
If imugraph's orientation is off by ε (nav frame), the field it fits is d̂ ≈ d_true + ε × n:
    d̂_y − d_true,y ≈ ψ cos δ + ε_x sin δ                                               (A1)
so the slow heading error ψ is the part of the field's heading deviation h = d_true,y / cos δ that d̂ did not
take (ψ = −h: heading follows the field; ψ = 0: d̂ took it all), plus what the tilt about north carries.
Printed: RMS of slow h, of slow ψ (ours, VQF); regression slopes ψ ≈ β h and the RMS of what is left.

Tilt and the velocity chain (B). A tilt error ε leaks gravity into the horizontal specific force,
R̂Δv ≈ RΔv + ε × ẑ g Δt, so the velocity chain that follows the accelerometer carries a phantom velocity e_v =
v̂ − v_opt with  ė_v,x = g ε_y,  ė_v,y = −g ε_x                                          (B1)
Printed: correlation of the slow ė_v with g·(ε_y, −ε_x), and the RMS of the slow e_v (m/s) and of the optical
velocity. If (B1) holds, the slow tilt is what the velocity process lets the accelerometer's mean drift by.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.b1_try import vqf_cached  # noqa: E402
from benchmarks.common import iter_broad, parse_options, pop_opts  # noqa: E402
from benchmarks.h4_decompose import CACHE  # noqa: E402
from benchmarks.v1_velocity_process import optical_velocities  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.calibration.result import n_mag_from_dip  # noqa: E402
from imugraph.evaluate import _align  # noqa: E402
from imugraph.geometry import logmap, quat_to_rotmat  # noqa: E402

SLOW_S = 2.0
G = 9.81


def rz(psi: float) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def truth_in_estimate_frame(q_est: np.ndarray, q_ref: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """(N, 3, 3) the reference orientation in the estimate's nav frame and time base (best alignment: ref ≈
    Rz(ψ)·est at est index j + shift; shift rounded to a sample), and ψ."""
    al = _align(q_est, q_ref, mask, 3.0, 0.25, True)
    shift = int(np.round(al.shift))
    R_ref = quat_to_rotmat(np.where(np.isfinite(q_ref), q_ref, [1.0, 0, 0, 0]))
    R_ref[~np.all(np.isfinite(q_ref), axis=1)] = np.nan
    R_ref = np.roll(R_ref, shift, axis=0)            # ref[j − shift] beside est[j]
    cands = []
    for p in (al.psi, -al.psi):
        R = np.einsum("ij,njk->nik", rz(p).T, R_ref)
        R_est = quat_to_rotmat(q_est)
        ok = mask & np.all(np.isfinite(R), axis=(1, 2))
        ang = np.linalg.norm(nav_errors(R_est[ok][::50], R[ok][::50]), axis=1)
        cands.append((np.sqrt(np.mean(ang**2)), R, p))
    _, R, p = min(cands, key=lambda c: c[0])
    return R, p


def nav_errors(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """(M, 3) nav-frame rotation errors ε = Log(R̂ Rᵀ), rad."""
    return np.stack([logmap(a @ b.T) for a, b in zip(R_est, R_true)])


def slow(x: np.ndarray, k: int) -> np.ndarray:
    """Centred moving average over k rows of a finite (M, ·) series, its mean removed."""
    x = np.asarray(x, float)
    x = x - np.nanmean(x, axis=0)
    ker = np.ones(k) / k
    return np.stack([np.convolve(c, ker, "same") for c in x.reshape(len(x), -1).T], axis=1).reshape(x.shape)


def fit(y: np.ndarray, x: np.ndarray) -> tuple[float, float, float]:
    """Slope β of y ≈ β x, correlation, RMS of y − β x."""
    b = float(x @ y / max(x @ x, 1e-30))
    return b, float(np.corrcoef(x, y)[0, 1]), float(np.sqrt(np.mean((y - b * x) ** 2)))


def fit2(y: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[float, float, float]:
    """Least squares y ≈ β₁ x₁ + β₂ x₂: β₁, β₂, RMS left."""
    X = np.c_[x1, x2]
    b, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(b[0]), float(b[1]), float(np.sqrt(np.mean((y - X @ b) ** 2)))


def spread(p: np.ndarray) -> tuple[float, float]:
    """(RMS about the mean, largest range over the axes) of positions (M, 3), finite rows only, m."""
    p = p[np.all(np.isfinite(p), axis=1)]
    return float(np.sqrt(np.mean(np.sum((p - p.mean(0)) ** 2, 1)))), float(np.max(np.ptp(p, axis=0)))


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.asarray(x) ** 2)))


def calibration_residual(R_true, m_cal, n_nav, mask, dip) -> dict:
    """(C) Is the field's deviation a calibration error? Body-frame residual e_b = D⁻¹(y − o) − Rᵀ n (truth R,
    imugraph's D, o) fitted by an affine map of the body-frame field, e_b ≈ M Rᵀn + c (12 parameters, least
    squares over every 5th movement sample): slow (2 s) RMS of the nav-frame y deviation (deg of heading) before
    and after (the slow average runs over the scored samples in order, across gaps)."""
    ok = mask & np.all(np.isfinite(m_cal), axis=1) & np.all(np.isfinite(R_true), axis=(1, 2))
    idx = np.flatnonzero(ok)[::5]
    m_b = np.einsum("nji,j->ni", R_true[idx], n_nav)
    e_b = m_cal[idx] - m_b
    X = np.c_[m_b, np.ones(len(idx))]
    coef, *_ = np.linalg.lstsq(X, e_b, rcond=None)
    left = e_b - X @ coef
    to_y = lambda e: np.einsum("ni,ni->n", R_true[idx][:, 1, :], e)        # nav y of a body-frame vector
    k = max(1, int(round(SLOW_S * 286 / 5)))                               # 2 s of the thinned samples
    hd = lambda e: float(np.rad2deg(rms(slow(to_y(e), k))) / np.cos(dip))
    return {"h_all": hd(e_b), "h_after_affine": hd(left), "M_norm": float(np.linalg.norm(coef[:3])),
            "c_norm": float(np.linalg.norm(coef[3]))}


def trial_report(num, s, mask, est, q_vqf) -> dict:
    from scipy.io import loadmat

    kf = np.asarray(est.info["keyframe_samples"])
    stride = int(est.info["stride"])
    R_true, psi = truth_in_estimate_frame(est.quat, s.quat, mask)
    R_est = quat_to_rotmat(est.quat)
    R_true_v, _ = truth_in_estimate_frame(q_vqf, s.quat, mask)
    R_vqf = quat_to_rotmat(q_vqf)
    cal = est.calibration
    m_cal = np.linalg.solve(cal.D, (cal.corrected(s.t, s.mag) - cal.o).T).T
    dip = np.deg2rad(cal.dip_deg)
    n_nav = n_mag_from_dip(dip)
    d_true = np.einsum("nij,nj->ni", R_true, m_cal) - n_nav            # (N, 3) the field's deviation
    out_c = calibration_residual(R_true, m_cal, n_nav, mask, dip)
    K = len(kf) - 1
    blocks = [slice(kf[k], kf[k + 1]) for k in range(K)]
    d_kf = np.stack([np.nanmean(d_true[b], axis=0) if np.isfinite(d_true[b]).any() else np.full(3, np.nan)
                     for b in blocks])
    d_hat = np.asarray(est.info["field_offsets"])[:K]
    ok = np.array([mask[b].mean() > 0.5 for b in blocks]) & np.all(np.isfinite(d_kf), axis=1)
    ok &= np.all(np.isfinite(R_true[kf[:K]]), axis=(1, 2)) & np.all(np.isfinite(R_true_v[kf[:K]]), axis=(1, 2))
    c = kf[:K][ok]                                        # keyframe samples used (movement, truth finite)
    eps = nav_errors(R_est[c], R_true[c])                              # ours, nav frame
    eps_v = nav_errors(R_vqf[c], R_true_v[c])                          # VQF, its own nav frame
    k2 = max(1, int(round(SLOW_S * s.rate / stride)))
    e_s, ev_s = np.rad2deg(slow(eps, k2)), np.rad2deg(slow(eps_v, k2))
    cd = np.cos(dip)
    h = np.rad2deg(slow(d_kf[ok, 1], k2)) / cd                         # field heading deviation, deg
    dh = np.rad2deg(slow(d_hat[ok, 1], k2)) / cd
    a1 = (dh - h)                                                       # (A1) left side / cos δ
    rhs = e_s[:, 2] + e_s[:, 0] * np.tan(dip)                           # ψ + ε_x tan δ: (ε × n)_y / cos δ
    out = {"trial": num, "psi_deg": float(np.rad2deg(psi)), "C": out_c}
    out["A"] = {"h_slow": rms(h), "dhat_slow": rms(dh), "psi_ours": rms(e_s[:, 2]), "psi_vqf": rms(ev_s[:, 2]),
                "A1_corr": float(np.corrcoef(a1, rhs)[0, 1]),
                "ours_on_h": fit(e_s[:, 2], h), "vqf_on_h": fit(ev_s[:, 2], h),
                "dhat_on_h": fit(dh, h),
                "ours_on_tilt_n": fit(e_s[:, 2], e_s[:, 0]), "vqf_on_tilt_n": fit(ev_s[:, 2], ev_s[:, 0]),
                "ours_2": fit2(e_s[:, 2], h, e_s[:, 0]), "vqf_2": fit2(ev_s[:, 2], h, ev_s[:, 0]),
                "tan_dip": float(np.tan(dip))}
    # (B) phantom velocity
    v_all = np.asarray(est.info["velocity"])[:K, :3]                    # every keyframe (∫v̂ runs over all)
    v_hat = v_all[ok]
    pos = np.asarray(loadmat(s.source)["opt_pos"], float)
    v_opt = optical_velocities(pos, c, s.rate)
    v_opt = v_opt @ rz(psi)                                            # ref → our nav: Rz(ψ)ᵀ v (ψ as aligned)
    fin = np.all(np.isfinite(v_opt), axis=1)
    e_v = np.where(fin[:, None], v_hat - v_opt, 0.0)
    dt_k = stride / s.rate
    de = np.gradient(e_v, dt_k, axis=0)
    de_s = slow(de[:, :2], k2)
    lhs = np.c_[G * np.deg2rad(e_s[:, 1]), -G * np.deg2rad(e_s[:, 0])]
    out["B"] = {"corr_x": float(np.corrcoef(de_s[:, 0], lhs[:, 0])[0, 1]),
                "corr_y": float(np.corrcoef(de_s[:, 1], lhs[:, 1])[0, 1]),
                "slope_x": fit(de_s[:, 0], lhs[:, 0])[0], "slope_y": fit(de_s[:, 1], lhs[:, 1])[0],
                "ev_slow": rms(slow(e_v[:, :2], k2)), "v_opt": rms(v_opt[fin][:, :2]),
                "v_hat": rms(v_hat[:, :2]),
                "p_hat": spread((np.cumsum(v_all, axis=0) * dt_k)[ok]), "p_opt": spread(pos[c]),
                "tilt_n": (rms(e_s[:, 0]), rms(ev_s[:, 0])), "tilt_w": (rms(e_s[:, 1]), rms(ev_s[:, 1]))}
    return out


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--opt",), max_args=1)
    opts, argv = pop_opts(argv)
    options = parse_options(opts)
    select = set(argv[0].split(",")) if argv else None
    check_trials(select)
    CACHE.mkdir(parents=True, exist_ok=True)
    for num, s, mask in iter_broad(select):
        est = calibrate(s, options, allow_weak=True)
        r = trial_report(num, s, mask, est, vqf_cached(num, s, CACHE))
        A, B, C = r["A"], r["B"], r["C"]
        print(f"{num} (A) slow RMS deg: field heading dev h {A['h_slow']:.3f}, d̂_y/cosδ {A['dhat_slow']:.3f}, "
              f"ψ ours {A['psi_ours']:.3f}, ψ VQF {A['psi_vqf']:.3f}; (A1) corr {A['A1_corr']:+.2f}")
        for name in ("ours_on_h", "vqf_on_h", "dhat_on_h", "ours_on_tilt_n", "vqf_on_tilt_n"):
            b, cc, res = A[name]
            print(f"     {name:14s} β {b:+.2f} corr {cc:+.2f} RMS left {res:.3f}")
        for name in ("ours_2", "vqf_2"):
            b1, b2, res = A[name]
            print(f"     {name:14s} ψ ≈ {b1:+.2f} h {b2:+.2f} ε_x (tan δ {A['tan_dip']:.2f}), RMS left {res:.3f}")
        print(f"   (B) tilt slow about north ours/VQF {B['tilt_n'][0]:.3f}/{B['tilt_n'][1]:.3f}, west "
              f"{B['tilt_w'][0]:.3f}/{B['tilt_w'][1]:.3f} deg; (B1) corr x {B['corr_x']:+.2f} (slope "
              f"{B['slope_x']:+.2f}), y {B['corr_y']:+.2f} ({B['slope_y']:+.2f}); slow phantom |e_v| "
              f"{B['ev_slow']:.3f} m/s, v̂ {B['v_hat']:.3f}, v_opt {B['v_opt']:.3f} m/s; position ∫v̂ RMS "
              f"{B['p_hat'][0]:.2f} range {B['p_hat'][1]:.2f} m, optical {B['p_opt'][0]:.2f} / {B['p_opt'][1]:.2f} m",
              flush=True)
        print(f"   (C) slow field heading deviation: {C['h_all']:.3f} deg; left after an affine body-frame map "
              f"(‖M‖ {C['M_norm']:.4f}, ‖c‖ {C['c_norm']:.4f}): {C['h_after_affine']:.3f} deg", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
