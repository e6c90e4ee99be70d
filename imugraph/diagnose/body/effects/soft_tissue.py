"""soft_tissue: the sensor moves relative to its segment (skin and muscle over the bone).

Physics (wobbling-mass / soft-tissue-artefact literature: thigh and shank IMUs and markers move 1–3 cm and
several degrees relative to the bone, with a damped 5–20 Hz resonance excited at heel strike, plus slow
gait-locked shifts with the joint angles). The tissue under the sensor is a mass on a spring–damper attached
to the bone; in the sensor frame the relative displacement x of such a mass obeys

    ẍ + 2ζω_n ẋ + ω_n² x = ω_n² u(t),    u = (ỹ_a − b̂_a) / g                                      (ST1)

per axis (u: the specific force the mass feels, in g; gravity included: its static part is a constant sag
that the fitted placement absorbs). The sensor's pose on the segment then varies as

    δp(t) = Σ_a c_a x_a(t) e_a                       translation (3 gains c_a, m per g)               (ST2)
    ψ(t)  = Σ_m k_m x_⊥m(t) + κ s(t)                 rotation about the segment's long axis u_ℓ,
                                                     x_⊥1,2: x along the two axes ⊥ u_ℓ; s: the slow
                                                     gait-locked term, u low-passed at 1.5 Hz along the
                                                     first ⊥ axis (follows the segment's inclination)  (ST3)
    d(t)  = δp(t) + ψ(t) u_ℓ × r_s                   the sensor's displacement from its rigid site,
                                                     r_s = the sensor's offset from the bone axis        (ST4)

Fit (first order, base (BE1)): the fitted sensor orientations, biases, levers and the neighbours stay fixed;
the per-sample joint-acceleration residual (BR4) of imugraph.diagnose.body.fit then changes exactly by

    Δjacc_i = −(d̈_i + 2 ω_i × ḋ_i + ω̇_i × d_i + ω_i × (ω_i × d_i))   (every joint block of the sensor)     (ST6)

(d̈ from the oscillator's own state: ẍ = ω_n²(u − x) − 2ζω_n ẋ; u from the rigid site's specific force as
the neighbours see it, `site_specific_force`). Only the translation (ST2) is fitted: a
rotation about the bone axis through the joint centres is a rigid rotation about an axis through each joint
centre, which leaves every lever l_j constant — no rigid-body residual sees it (the reason issue 4 found the
thigh's axial rotation "whatever the body model does"); ψ stays in the injection (it is physics) and out of
the fit. The keyframe channels are left to the base fit (the displacement bent its positions: measured on a
simulated walk, the first-order position-channel correction recovered 0.03 % of an injected 7 mm wobble).
Parameters: c (3) + ω_n, ζ (grid {4, 6, 9, 13, 18} Hz × {0.25, 0.5}, chosen by the training residual): 5.

Relevance: RMS of the fitted |d| ≥ 1 mm: through a 0.2 m lever to a joint, ≈ 0.3° of segment orientation (the
single-IMU accelerometer_bias threshold is also 0.3° of tilt). A first threshold of 3 mm (the joint model's σ)
left a detected 12 mm/g thigh tissue (injected translation RMS 1.3 mm, fitted 0.7 mm, held-out G +1.8 nats per
sample in all 5 folds, shrink 0.39) irrelevant.

Injection (RANGES): f_n 5–18 Hz (at most 0.3 × the sampling rate), ζ 0.2–0.5; tissue compliance
|c| = 5–20 mm per g in a random direction (the translation follows the site's specific force: a quasi-static
part with the gait's inertial loads and the resonance where the motion excites it); axial rotation gains
|k| = 0.02–0.07 rad per g and a slow term of 2–6° peak-to-peak; optionally over a window (raised-cosine
envelope: a strap loosening). A displacement RMS target instead (first version, 4–12 mm) put up to 88 m/s² of
17 Hz acceleration into a simulated thigh, far above the soft-tissue accelerations reported at heel strike. The measurements change exactly to first order in (d, ψ):

    ω' = ω + ψ̇ u_ℓ − ψ u_ℓ × ω,
    f' = f + d̈ + 2 ω × ḋ + ω̇ × d + ω × (ω × d) − ψ u_ℓ × f                                        (ST5)

with u_ℓ and r_s from the NOMINAL placement (imugraph.body.placement: the injector does not know the fit).
"""

from __future__ import annotations

import numpy as np
from scipy.signal import butter, cont2discrete, filtfilt, lfilter, ss2tf

from imugraph.diagnose.body.effects.base import (BodyCorrection, BodyEffect, changed_columns, linear_fit,
                                                  pick_sensor, with_sensor)
from imugraph.diagnose.effects.base import envelope, random_window, replace_session

RANGES = {"f_n_hz": (5.0, 18.0), "zeta": (0.2, 0.5), "compliance_m_per_g": (0.005, 0.02),
          "rotation_rad_per_g": (0.02, 0.07), "slow_ptp_deg": (2.0, 6.0)}
GRID_F_HZ = (4.0, 6.0, 9.0, 13.0, 18.0)
GRID_ZETA = (0.25, 0.5)
SLOW_HZ = 1.5
RELEVANT_M = 0.001
G0 = 9.81


def oscillator(u: np.ndarray, dt: float, f_n: float, zeta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ST1) driven by u (N, 3): x, ẋ, ẍ (N, 3) from rest (zero-order-hold discretisation)."""
    w = 2 * np.pi * f_n
    A = np.array([[0.0, 1.0], [-w * w, -2 * zeta * w]])
    B = np.array([[0.0], [w * w]])
    Ad, Bd = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), dt, method="zoh")[:2]
    out = []
    for C in (np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]])):
        b, a = ss2tf(Ad, Bd, C, np.zeros((1, 1)))
        out.append(lfilter(b[0], a, u - u[:1], axis=0))      # from rest at the static equilibrium x = u₀
    x, xd = out[0] + u[:1], out[1]
    xdd = w * w * (u - x) - 2 * zeta * w * xd
    return x, xd, xdd


def perpendicular_axes(u_long: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes ⊥ u_ℓ (the first as close to the sensor's z as possible: out of the skin)."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(u_long[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = ref - (ref @ u_long) * u_long
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u_long, e1)


def slow_signal(u: np.ndarray, dt: float, e1: np.ndarray) -> np.ndarray:
    """s(t) of (ST3): u low-passed at SLOW_HZ along e1, minus its median."""
    b, a = butter(2, min(SLOW_HZ * 2 * dt, 0.99))
    s = filtfilt(b, a, u @ e1) if u.shape[0] > 15 else u @ e1
    return s - np.median(s)


def second_derivative(x: np.ndarray, dt: float) -> np.ndarray:
    return np.gradient(np.gradient(x, dt, axis=0), dt, axis=0)


def site_specific_force(sf, t: np.ndarray, ses) -> np.ndarray:
    """(N, 3) the specific force of the sensor's RIGID site, which drives the tissue (ST1), from the neighbours:
    the joint-centre acceleration each neighbour q sees (R̂_q ĵ_q of (BR4)), brought to the site through the
    sensor's own rates, f_site = R̂_sᵀ R̂_q ĵ_q − Exp(ω dt/2)(ω̇ × l_j + ω × (ω × l_j)), mean over the joints.
    The sensor's own accelerometer would drive the oscillator with its own output (measured on a simulated
    walk: a 17 Hz, 7.7 mm wobble was fitted as 9 Hz, 1.9 mm). No neighbours: the sensor's accelerometer."""
    from imugraph.diagnose.body.fit import joint_acceleration

    if not sf.pairs:
        return ses.acc - sf.b_acc
    zero = np.zeros_like(ses.acc)
    out = [np.einsum("nba,nb->na", sf.R_samples, p["n_j_other"])
           - joint_acceleration(t, ses.gyr, zero, sf.b_gyr, 0.0, p["lever"]) for p in sf.pairs]
    return np.mean(out, axis=0)


class SoftTissue(BodyEffect):
    name = "soft_tissue"
    channel = "jacc"
    windowed = True
    ranges = RANGES

    # ------------------------------------------------------------------------------------------ injection
    def inject(self, session, rng, *, sensor=None, window=None, strength=None):
        """(ST5) on one sensor. strength: tissue compliance |c| in m per g (default random); window: (t0, t1) or "random"
        (a random 30–70 % of the session) or None (the whole session)."""
        from imugraph.body.placement import nominal_placement

        sensor = pick_sensor(session, rng, sensor)
        ses = session.sensors[sensor]
        skel = session.skeleton
        t, dt = ses.t, float(np.median(ses.dt))
        nom = nominal_placement(skel, sensor)
        e = np.asarray(skel.ends[skel.index(sensor)], float)
        u_long = nom.bRs.T @ (e / np.linalg.norm(e))
        r_b = np.asarray(nom.b_pos, float) - (np.asarray(nom.b_pos, float) @ (e / np.linalg.norm(e))) * e / np.linalg.norm(e)
        r_s = nom.bRs.T @ r_b                                                # sensor offset from the bone axis
        f_n = min(rng.uniform(*RANGES["f_n_hz"]), 0.3 / dt)
        zeta = rng.uniform(*RANGES["zeta"])
        u = ses.acc / G0
        x, xd, xdd = oscillator(u, dt, f_n, zeta)
        xc = x - np.mean(x, axis=0)
        if window == "random":
            window = random_window(ses, rng, frac=(0.3, 0.7))
        env = envelope(t, window, 1.0) if window is not None else np.ones(t.size)
        d_dir = rng.standard_normal(3)
        d_dir /= np.linalg.norm(d_dir)
        c = float(strength) if strength is not None else rng.uniform(*RANGES["compliance_m_per_g"])       # (ST2)
        e1, e2 = perpendicular_axes(u_long)
        k_dir = rng.standard_normal(2)
        k = rng.uniform(*RANGES["rotation_rad_per_g"]) / max(float(np.linalg.norm(k_dir)), 1e-12)
        psi_fast = env * (xc @ e1 * k_dir[0] + xc @ e2 * k_dir[1])
        s = env * slow_signal(u, dt, e1)
        kappa = np.deg2rad(rng.uniform(*RANGES["slow_ptp_deg"])) / max(float(np.ptp(s)), 1e-12)
        s_d, s_dd = np.gradient(s, dt), second_derivative(s, dt)                    # slow: numerical is exact enough
        fast = [(xc, xd, xdd)[m] @ e1 * k_dir[0] + (xc, xd, xdd)[m] @ e2 * k_dir[1] for m in range(3)]
        psi = env * k * fast[0] + kappa * s                                                          # (ST3)
        psi_d = env * k * fast[1] + kappa * s_d
        psi_dd = env * k * fast[2] + kappa * s_dd
        arm = np.cross(u_long, r_s)
        d = env[:, None] * c * xc * d_dir + psi[:, None] * arm                                        # (ST4)
        dd = env[:, None] * c * xd * d_dir + psi_d[:, None] * arm          # oscillator states: exact derivatives
        ddd = env[:, None] * c * xdd * d_dir + psi_dd[:, None] * arm      # (the envelope's 1 s ramps neglected)
        w = ses.gyr
        wd = np.gradient(w, t, axis=0)
        gyr = w + psi_d[:, None] * u_long - psi[:, None] * np.cross(u_long, w)                         # (ST5)
        acc = (ses.acc + ddd + 2 * np.cross(w, dd) + np.cross(wd, d) + np.cross(w, np.cross(w, d))
               - psi[:, None] * np.cross(u_long, ses.acc))
        on = env > 0.5
        truth = {"params": {"f_n_hz": float(f_n), "zeta": float(zeta), "compliance_m_per_g": float(c),
                            "direction": d_dir.tolist(),
                            "translation_rms_m": float(np.sqrt(np.mean(np.sum((c * xc[on] * d_dir) ** 2, axis=1)))),
                            "acceleration_rms_ms2": float(np.sqrt(np.mean(np.sum(ddd[on] ** 2, axis=1)))),
                            "rotation_rms_deg": float(np.rad2deg(np.sqrt(np.mean((k * psi_fast[on]) ** 2)))),
                            "sensor_offset_from_bone_axis_m": float(np.linalg.norm(r_s)),
                            "slow_ptp_deg": float(np.rad2deg(np.ptp(kappa * s))),
                            "displacement_rms_m": float(np.sqrt(np.mean(np.sum(d[on] ** 2, axis=1))))},
                 "sensor": sensor, "t_start": None if window is None else float(window[0]),
                 "t_end": None if window is None else float(window[1])}
        new = replace_session(ses, gyr=gyr, acc=acc, name_suffix="+soft_tissue")
        return with_sensor(session, sensor, new, {"injected": {self.name: truth}}), truth

    # ----------------------------------------------------------------------------------------------- fit
    def columns(self, bfit, sensor: str, f_n: float, zeta: float) -> tuple[list, list]:
        """(ST6) columns (channel → change of the residuals per unit gain c_a) and d per unit gain. Against a
        full refit θ* of this sensor (bfit.info["refit_of"] == sensor: θ* was fitted to the data with the effect
        removed, its positions no longer follow the wobble) the keyframe channels change too: their (BE1)
        columns of the accelerometer change −(d̈ + …) are added (exact: linear)."""
        sf = bfit.sensors[sensor]
        ses = bfit.session.sensors[sensor]
        t = np.asarray(bfit.session.t, float)
        dt = float(np.median(ses.dt))
        x, xd, xdd = oscillator(site_specific_force(sf, t, ses) / G0, dt, f_n, zeta)
        x = x - np.mean(x, axis=0)
        w = ses.gyr - sf.b_gyr
        wd = np.gradient(w, t, axis=0)
        P = len(sf.pairs)
        cols, ds, dacc = [], [], []
        for a in range(3):
            E = np.zeros(3)
            E[a] = 1.0
            d, dd, ddd = x[:, a:a + 1] * E, xd[:, a:a + 1] * E, xdd[:, a:a + 1] * E
            dj = -(ddd + 2 * np.cross(w, dd) + np.cross(wd, d) + np.cross(w, np.cross(w, d)))          # (ST6)
            if bfit.info.get("refit_of") == sensor:
                col = changed_columns(bfit, sensor, [dj], "acc")[0]
            else:
                col = {c: np.zeros_like(r) for c, r in sf.residuals.items()}
            col["jacc"] = np.tile(dj, (1, P)) if P else np.zeros((t.size, 0))
            cols.append(col)
            ds.append(d)
            dacc.append(dj)
        return cols, (ds, dacc)

    def fit(self, bfit, sensor, train, sigma) -> BodyCorrection:
        best = None
        base = bfit.sensors[sensor].residuals
        cache = bfit.info.setdefault("_soft_tissue_columns", {})
        for f_n in GRID_F_HZ:
            for zeta in GRID_ZETA:
                key = (sensor, f_n, zeta)
                if key not in cache:
                    cache[key] = self.columns(bfit, sensor, f_n, zeta)
                cols, ds = cache[key]
                theta, res = linear_fit(base, cols, sigma, train)
                cost = sum(float(np.nansum((res[c][train[c]] / sigma[c]) ** 2)) for c in res if res[c].shape[1])
                if best is None or cost < best[0]:
                    best = (cost, f_n, zeta, theta, res, ds)
        _, f_n, zeta, theta, res, (ds, dacc) = best
        d = sum(th * di for th, di in zip(theta, ds))
        rms = float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
        params = {"f_n_hz": f_n, "zeta": zeta, "translation_gain_m_per_g": theta.tolist(), "displacement_rms_m": rms}
        return BodyCorrection(self.name, sensor, params, 5, self.channel, res,
                              size={"value": rms, "threshold": RELEVANT_M, "unit": "m"},
                              deltas={"acc": sum(th * da for th, da in zip(theta, dacc))})        # (ST6): y' = y − d̈ − …


EFFECT = SoftTissue()
