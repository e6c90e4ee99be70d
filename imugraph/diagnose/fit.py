"""The user's base model of one IMU, fitted to a recording, its residuals, and a simulation from it.

Base model (the simplest honest one; DESIGN.md conventions, Kok & Schön 2016):

    b_gyr,j = ω_j + δ_ω + e_ω             gyro: rate + ONE constant bias + white noise                   (B1)
    b_acc,j = bRn,j · (0, 0, g) + e_a        accelerometer: gravity only, NO linear acceleration           (B2)
    b_mag(t_j + τ_m) = D · bRn,j · n_mag + o + e_m    magnetometer: its own lag τ_m, no disturbance windows (B3)

fitted with `imugraph.calibration.ml.calibrate` (linear_acceleration="noise", disturbance_windows=False,
bias_segment_s=0: one bias segment — a drifting bias is the gyro_bias_drift effect, not the base model):
per-sample nRb, D, o, dip, gyro bias, noise σ per channel. The magnetometer's lag behind the gyro τ_m is
part of the base model, as it is of `imugraph calibrate`'s default model (`compensate_mag_delay=True`,
calibration.json `mag_delay_s`): a recording is fitted with its field on the gyro's time base,
`undelay_magnetometer(t, b_mag, τ_m)` (whole samples), τ_m from the calibration's own initial estimate
(`calibration.alignment.estimate_mag_delay`: BROAD 8.6–10.2 ms on every rotating trial, a property of
the sensor). τ_m is signed, as the calibration's: the field–gyro timing of a sensor whose gyro filter
delays more than its magnetometer is a calibrated property too. The price: an injected gyro delay moves
the field along with the late gyro and is then seen in the accelerometer only (BROAD 01 + 31.6 ms gyro
delay: τ_m −21.4 ms). Clamping τ_m ≥ 0 was measured and not kept: that case stayed none (time_offset
on mag 4.4 samples, (A2) 0.19) and sim01 + 21 ms gyro delay fell from shrink 0.61 to 0.50.
The whole-sample shift leaves τ_f = τ_m − round(τ_m/Δt)·Δt (≤ ½ sample), which on fast crops was a
relevant misfit (BROAD 07: the magnetometer's whitened cost 14–22 % above its value with τ_f removed,
named by time_offset; docs/diagnose.md §4 G2). It goes into the PREDICTION (issue 5, G6):

    h_mag(t_j) = D · R(t_j − τ_f)ᵀ n_mag + o,   R(t_j − τ_f) = R̂_j Exp(−τ_f ω̂_j)                          (B3')

applied as a model offset, not an interpolation of the data (which averages neighbouring samples'
noise): a first fit gives R̂, ω̂, D; the field is then fitted as b_mag − (h(t_j − τ_f) − h(t_j)) of that
fit (`subsample_lag_offset`; every sample keeps its own noise), so that the final fit's residual is
b_mag − h_mag(t_j − τ_f) to first order in the change between the two fits. One extra calibration per
fresh fit; the simulations are drawn on the fitted (lag-free) time base and need none.
`Fit.session` is that aligned session and `Fit.info["mag_delay_s"]` holds τ_m (`mag_subsample_s` τ_f). The delay
is estimated only for a fresh fit (`initial` not given): the refits and the simulations' fits work on
data already on the gyro's time base.

Residuals (raw units, y − h(x̂), NaN where a channel has no sample):

    gyr_j = b_gyr,j − δ_ω,s(j) − ω̂_j,   ω̂_j = Log(R̂_jᵀ R̂_{j+1}) / Δt_j                              (R1)
    acc_j = b_acc,j − R̂_jᵀ (0, 0, g)                                                                     (R2)
    mag_j = b_mag,j − (D R̂_jᵀ n_mag + o)                                                                 (R3)

About (R1): between keyframes the fitted orientation is the gyro integrated at the bias of the solver's
last linearisation, blended (slerp) with the backward integration from the next keyframe, so per sample
ω̂_j = b_gyr,j − b̂ + c_k: the gyro's white noise cancels and what is left is, in every keyframe interval k,
the (almost constant) rate c_k by which the accelerometer and magnetometer pulled the keyframes away from
the integrated gyro. Its std for a consistent model is ≈ σ_ω/√M (M samples per keyframe interval), the σ
used to whiten it. The last sample has no successor: NaN.

`simulate_from_fit` draws a session from the fitted model: the fitted trajectory is the truth (its rate
ω̂_j constant over [t_j, t_{j+1}), linear acceleration 0), with the fitted bias segments, D, o, dip, g and
white noise at the fitted σ, on the real recording's time base and magnetometer sampling pattern.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from imugraph.calibration.result import Calibration
from imugraph.errors import SessionError
from imugraph.geometry import logmap, quat_to_rotmat, rotmat_to_quat
from imugraph.io.session import Session

CHANNELS = ("gyr", "acc", "mag")
# (B3') opt-in (G6): measured only together with effects/joint.ENABLED (docs/diagnose.md §4 G6); off by
# default until measured alone on the harness.
SUBSAMPLE_LAG = False


@dataclass
class Fit:
    """The base model fitted to one session.

    Attributes:
        session: the data that were fitted: the recording with its field on the gyro's time base (B3).
        nRb: (N, 3, 3) fitted orientation body → nav per sample.
        calibration: D, o, dip_deg, gyro_bias (mean), noise {"gyr", "acc", "mag": (3,) σ}.
        g: gravity magnitude used, m/s².
        residuals: channel → (N, 3) raw-unit residuals (R1)–(R3), NaN where no sample.
        sigma: channel → (3,) σ used to whiten (gyr: σ_ω/√M, see module doc; acc, mag: fitted σ).
        b_gyr_bias: (N, 3) gyro bias of each sample (the fitted segment values), rad/s.
        b_omega: (N, 3) fitted body rate ω̂_j = Log(R̂_jᵀR̂_{j+1})/Δt_j, rad/s (last row repeats).
        keyframe_samples: (K,) sample index of each keyframe of the fit.
        info: extra facts of the solve (stride, iterations, keyframe_hz).
    """

    session: Session
    nRb: np.ndarray
    calibration: Calibration
    g: float
    residuals: dict
    sigma: dict
    b_gyr_bias: np.ndarray
    b_omega: np.ndarray
    keyframe_samples: np.ndarray
    info: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.session.n

    def whitened(self, channel: str) -> np.ndarray:
        """(N, 3) residuals of `channel` divided by its σ (NaN where no sample)."""
        return self.residuals[channel] / self.sigma[channel]

    def predicted(self) -> dict:
        """channel → (N, 3) model prediction h(x̂) (gyr includes the bias) in raw units."""
        cal = self.calibration
        bRn = np.transpose(self.nRb, (0, 2, 1))
        acc = bRn @ np.array([0.0, 0.0, self.g])                                   # (B2)
        mag = (bRn @ cal.n_mag) @ np.asarray(cal.D).T + np.asarray(cal.o)           # (B3)
        return {"gyr": self.b_omega + self.b_gyr_bias, "acc": acc, "mag": mag}

    def residuals_with(self, *, gyr=None, acc=None, mag=None) -> dict:
        """Residuals (R1)–(R3) of other (corrected) measurement arrays against the same fitted trajectory
        and parameters: what an effect's first-order refit evaluates (x̂ fixed). Channels not given are
        copied from `residuals`."""
        out = {c: self.residuals[c].copy() for c in CHANNELS}
        pred = self.predicted()
        for c, y in (("gyr", gyr), ("acc", acc), ("mag", mag)):
            if y is not None:
                r = np.asarray(y, float) - pred[c]
                if c == "gyr":
                    r[-1] = np.nan
                out[c] = r
        return out


def base_options(keyframe_hz: float = 5.0):
    """The calibration Options of the base model (B1)–(B3)."""
    from imugraph.calibration.ml import Options

    # gyro scale/misalignment is an effect (gyro_scale), not the base; rows paired as recorded
    # (acc_lead_samples 0, as the simulation of the fit and the effects' refits pair them): a timing
    # between the channels is the time_offset effect's to find (with calibrate's ½ here, BROAD 16's linear
    # acceleration scored (A2) +0.13 instead of +0.67 — the refits and the base disagreed on the pairing)
    return Options(linear_acceleration="noise", disturbance_windows=False, compensate_mag_delay=False,
                   keyframe_hz=keyframe_hz, bias_segment_s=0.0, field_sigma=None,  # no field perturbation
                   gyro_map=False, acc_lead_samples=0.0)


def body_rate(nRb: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """(N, 3) ω_j = Log(R_jᵀ R_{j+1}) / Δt_j, the rate constant over [t_j, t_{j+1}); last row repeats."""
    rel = np.transpose(nRb[:-1], (0, 2, 1)) @ nRb[1:]
    w = logmap(rel) / dt[:-1, None]
    return np.vstack([w, w[-1:]]) if len(w) else np.zeros((len(nRb), 3))


def fit_base(session: Session, options=None, initial=None, extended: dict | None = None,
             align_mag: bool = True) -> Fit:
    """Fit the base model (B1)–(B3) to a session (calibration, bias segments, noise, trajectory).

    Args:
        session: the recording (not modified).
        options: `imugraph.calibration.ml.Options`; default `base_options()`. Its linear acceleration,
            disturbance-window and delay settings are forced to the base model's.
        initial: start of the ML loop (attributes D, o, dip_rad, gyro_bias, noise, rest, coverage);
            default `imugraph.calibration.initial.initial_calibration` (regularised when D, o are not
            identifiable). `fit_simulation` starts a simulation's fit from the real fit.
        extended: Options fields set AFTER the base model's (e.g. {"disturbance_windows": True}): the fit
            of an extended model that imugraph.calibration.ml has jointly (imugraph.diagnose.refit); the
            residuals (R1)–(R3) stay those of the base model's terms at the extended model's estimate.
        align_mag: with `initial` None, put the field on the gyro's time base by the magnetometer lag τ_m
            of the initial estimate (module doc, (B3)); False: τ_m = 0 (the model without the lag).

    Raises:
        SessionError: the session is too short or has no magnetometer samples.
        CalibrationError: the data do not allow a calibration (too little rotation, ...).
    """
    from imugraph.calibration.ml import _bias_segments, _per_sample_bias, calibrate, stride_for
    from imugraph.factors.gyro import keyframe_layout

    opt = options or base_options()
    opt = replace(opt, linear_acceleration="noise", disturbance_windows=False, compensate_mag_delay=False,
                  bias_segment_s=0.0)
    if extended:
        opt = replace(opt, **extended)
    if session.n < 4 * stride_for(session, opt.keyframe_hz):
        raise SessionError(session.source, "t", f"{session.n} samples",
                           f"at least {4 * stride_for(session, opt.keyframe_hz)} samples to diagnose")
    if not np.any(session.mag_valid):
        raise SessionError(session.source, "mag", "no magnetometer sample", "a magnetometer signal")
    delay = 0.0
    if initial is None:
        initial = _initial(session)
        delay = float(getattr(initial, "mag_delay_s", 0.0) or 0.0) if align_mag else 0.0
        if delay != 0.0:                                                            # (B3) τ_m
            from imugraph.calibration.alignment import undelay_magnetometer

            session = session.with_mag(undelay_magnetometer(session.t, session.mag, delay))
            frac = delay - np.round(delay / float(np.median(session.dt))) * float(np.median(session.dt))
            if SUBSAMPLE_LAG and abs(frac) > 1e-9:                                  # (B3') the ≤ ½ sample left
                first = fit_base(session, opt, initial=initial)
                session = session.with_mag(session.mag - subsample_lag_offset(first, frac))
                fit = fit_base(session, opt, initial=initial)
                fit.info.update(mag_delay_s=delay, mag_subsample_s=frac)
                return fit
    est = calibrate(session, opt, initial=initial, allow_weak=True)
    cal = est.calibration
    nRb = quat_to_rotmat(est.quat)
    g = float(est.info["g"])
    stride = int(est.info["stride"])
    kf, skf = keyframe_layout(session.n, stride, session.dt)      # a keyframe at every long gap, as calibrate
    seg = _bias_segments(session, kf, opt.bias_segment_s)
    bias_seg = np.asarray(est.info["gyro_bias_segments"], float)
    b_bias = _per_sample_bias(bias_seg, seg, skf)                                   # (B1) δ_ω,s(j)
    b_omega = body_rate(nRb, session.dt)                                            # (R1) ω̂_j
    sigma = {"gyr": np.asarray(cal.noise["gyr"], float) / np.sqrt(stride),
             "acc": np.asarray(cal.noise["acc"], float), "mag": np.asarray(cal.noise["mag"], float)}
    fit = Fit(session, nRb, cal, g, {}, sigma, b_bias, b_omega, kf,
              {"stride": stride, "keyframe_hz": opt.keyframe_hz, "iterations": cal.iterations,
               "converged": cal.converged, "bias_segments": bias_seg, "identifiable":
               cal.coverage.get("identifiable", True) if isinstance(cal.coverage, dict) else True,
               "rest": getattr(initial, "rest", None), "mag_delay_s": delay})
    fit.residuals = _raw_residuals(fit)
    return fit


def subsample_lag_offset(fit: Fit, frac_s: float) -> np.ndarray:
    """(N, 3) h_mag(t_j − τ_f) − h_mag(t_j) of a fit: the predicted field at the orientation the body had
    τ_f earlier, R(t_j − τ_f) = R̂_j Exp(−τ_f ω̂_j), minus the prediction at R̂_j (B3')."""
    from imugraph.geometry import expmap

    cal = fit.calibration
    R_lag = fit.nRb @ expmap(-frac_s * fit.b_omega)
    h = (np.transpose(fit.nRb, (0, 2, 1)) @ cal.n_mag) @ np.asarray(cal.D).T
    h_lag = (np.transpose(R_lag, (0, 2, 1)) @ cal.n_mag) @ np.asarray(cal.D).T
    return h_lag - h


def _initial(session: Session):
    """The calibration's own initial estimate, or the regularised one when D, o are not identifiable."""
    from imugraph.calibration.initial import initial_calibration
    from imugraph.calibration.ml import weak_initial
    from imugraph.errors import CalibrationError

    try:
        return initial_calibration(session)
    except CalibrationError as exc:
        return weak_initial(session, str(exc))


def fit_simulation(sim: Session, real: Fit, options=None) -> Fit:
    """Fit the base model to a simulation drawn from `real`, started from the real fit: its D, o, dip,
    bias, noise levels (the gyro σ, measured at rest on the real data, is not re-estimated by the ML
    loop) and the real rest mask (the simulation's accelerometer is white noise at the fitted σ, which
    hides rest from the detector)."""
    from types import SimpleNamespace

    cal = real.calibration
    init = SimpleNamespace(D=np.asarray(cal.D, float), o=np.asarray(cal.o, float), dip_rad=cal.dip_rad,
                           gyro_bias=np.asarray(cal.gyro_bias, float),
                           noise={c: np.asarray(cal.noise[c], float) for c in CHANNELS},
                           rest=real.info.get("rest"), coverage=dict(cal.coverage or {}))
    return fit_base(sim, options or base_options(real.info.get("keyframe_hz", 5.0)), initial=init)


def _raw_residuals(fit: Fit) -> dict:
    """Residuals (R1)–(R3) of the fit's own session."""
    s = fit.session
    pred = fit.predicted()
    out = {}
    for c, y in (("gyr", s.gyr), ("acc", s.acc), ("mag", s.mag)):
        r = np.asarray(y, float) - pred[c]
        r[~np.all(np.isfinite(y), axis=1)] = np.nan
        out[c] = r
    out["gyr"][-1] = np.nan
    return out


def simulate_from_fit(fit: Fit, rng: np.random.Generator, name: str | None = None) -> Session:
    """A session drawn from the fitted base model along the fitted motion (module doc).

    The truth of the simulation is the fitted trajectory: gyro = ω̂ + bias segments + e_ω (B1),
    acc = R̂ᵀ(0, 0, g) + e_a (B2), mag = D R̂ᵀ n_mag + o + e_m (B3), e ~ N(0, σ²) per axis at the fitted
    σ; magnetometer rows are NaN where the real recording has none. `quat` = the fitted nRb.
    """
    from imugraph.sim.sensors import SensorParams, simulate_imu

    cal = fit.calibration
    s = fit.session
    params = SensorParams(gyro_noise=np.asarray(cal.noise["gyr"], float),
                          acc_noise=np.asarray(cal.noise["acc"], float),
                          mag_D=np.asarray(cal.D, float), mag_o=np.asarray(cal.o, float),
                          dip_rad=cal.dip_rad, field_norm=1.0,
                          mag_noise=np.asarray(cal.noise["mag"], float), g=fit.g)
    quat = rotmat_to_quat(fit.nRb)
    sim = simulate_imu(s.t, quat, fit.b_omega, np.zeros((s.n, 3)), params, rng,
                       name=name or f"{s.name}_sim")
    gyr = sim.gyr + fit.b_gyr_bias                                                  # (B1) bias segments
    mag = sim.mag.copy()
    mag[~s.mag_valid] = np.nan
    meta = dict(sim.meta, simulated_from=s.name)
    return Session(t=s.t.copy(), gyr=gyr, acc=sim.acc, mag=mag, quat=quat, movement=s.movement,
                   source=f"<simulation of {s.source}>", name=sim.name, meta=meta)
