"""The effect interface for body sessions (as imugraph.diagnose.effects.base, per sensor).

An effect acts on ONE sensor: `inject` adds it to a body session (the truth names the sensor), `fit` extends
the base model of that sensor with the effect's parameters, estimated on training keyframe intervals only, and
returns a `BodyCorrection` holding the extended model's residuals on every interval (the held-out ones too).

First-order refit (all body effects): the fitted trajectory, biases and levers stay fixed; the effect's
parameters θ enter the residuals (BR1)–(BR3) of imugraph.diagnose.body.fit linearly,

    r'(θ) = r + Σ_p θ_p c_p,    c_p = r(y + Δy_p) − r(y)   (Δy_p: the measurement change of unit θ_p)      (BE1)

(exact for accelerometer changes: the preintegrated Δṽ, Δp̃ are linear in ỹ_a; first order for gyro changes),
and θ minimises Σ_train Σ_c ‖r'_c / σ_c‖² over the training rows (σ: the model's residual level (BG1)):
linear least squares on the whitened stacked channels. Training masks are per channel ({channel: rows}: the
keyframe-interval channels and the per-sample (BR4) have their own time bases).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from imugraph.diagnose.body.fit import CHANNELS, BodyFit
from imugraph.errors import SessionError


@dataclass
class BodyCorrection:
    """The base model of one sensor extended by one effect.

    Attributes:
        name: effect name. sensor: the sensor (segment) it acts on. params: JSON-ready fitted parameters.
        n_params: free parameters added. channel: channel holding the evidence. residuals: channel →
        (K−1, d) residuals of the extended model. t_start/t_end: window (None: global). size: relevance.
        deltas: the measurement changes that remove the fitted effect (for the full refit, body/refit.py).
    """

    name: str
    sensor: str
    params: dict
    n_params: int
    channel: str
    residuals: dict
    t_start: Optional[float] = None
    t_end: Optional[float] = None
    size: dict = field(default_factory=dict)
    deltas: dict = field(default_factory=dict, repr=False)   # {"gyr"/"acc": (N, 3)}: y' = y + Δ removes the effect


class BodyEffect:
    """One effect of the body library: subclasses set name/channel/ranges and implement inject and fit."""

    name: str = ""
    channel: str = ""
    windowed: bool = False
    ranges: dict = {}

    def inject(self, session, rng: np.random.Generator, *, sensor: str | None = None, window=None,
               strength=None):
        """(modified BodySession, truth {"params", "sensor", "t_start", "t_end"})."""
        raise NotImplementedError

    def fit(self, bfit: BodyFit, sensor: str, train: np.ndarray, sigma: dict) -> BodyCorrection:
        raise NotImplementedError


class PerSensorEffect(BodyEffect):
    """A single-IMU effect applied to one sensor of a body session: `single` is the single-IMU module's
    EFFECT, whose injection (ranges, draws) is reused on the chosen sensor's Session."""

    single = None

    @property
    def ranges(self) -> dict:
        """The single-IMU module's injection ranges."""
        return self.single.ranges

    def inject(self, session, rng: np.random.Generator, *, sensor: str | None = None, window=None,
               strength=None):
        sensor = pick_sensor(session, rng, sensor)
        new, truth = self.single.inject(session.sensors[sensor], rng, window=window, strength=strength)
        truth = dict(truth, sensor=sensor)
        return with_sensor(session, sensor, new, {"injected": {self.name: truth}}), truth


def check_sensor(session, sensor: str) -> None:
    if sensor not in session.sensors:
        raise SessionError(getattr(session, "source", "<memory>"), "sensor", f"'{sensor}'",
                           f"one of {sorted(session.sensors)}")


def pick_sensor(session, rng: np.random.Generator, sensor: str | None) -> str:
    """The given sensor (checked) or a random one."""
    if sensor is None:
        return str(rng.choice(sorted(session.sensors)))
    check_sensor(session, sensor)
    return sensor


def with_sensor(session, sensor: str, new_session, meta: dict, name: str | None = None):
    """A copy of the body session with one sensor's Session replaced (inputs untouched); name: the copy's
    name (None: the session's + the injected effects' names)."""
    from imugraph.io.body_session import BodySession

    sensors = dict(session.sensors)
    sensors[sensor] = new_session
    m = dict(session.meta)
    m.update(meta)
    if name is None:
        name = session.name + "+" + "+".join(meta.get("injected", {}).keys())
    return BodySession(session.t, sensors, session.skeleton, session.truth, session.source, name, m)


def linear_fit(base: dict, columns: list, sigma: dict, train: np.ndarray) -> tuple[np.ndarray, dict]:
    """(BE1): θ and the corrected residuals r + Σ θ_p c_p (channel → rows × d) from columns (list of
    channel → rows × d changes per unit θ_p), LS on the whitened stacked channels over the training rows
    (train: channel → row mask)."""
    A_rows, y_rows = [], []
    for c in CHANNELS:
        if base[c].shape[1] == 0:
            continue
        ok = train[c] & np.all(np.isfinite(base[c]), axis=1)
        s = sigma[c]
        y_rows.append((base[c][ok] / s).reshape(-1))
        A_rows.append(np.stack([(col[c][ok] / s).reshape(-1) for col in columns], axis=1))
    A, y = np.concatenate(A_rows), np.concatenate(y_rows)
    scale = np.maximum(np.sqrt(np.sum(A * A, axis=0)), 1e-300)
    theta = np.linalg.lstsq(A / scale, -y, rcond=None)[0] / scale
    out = {c: base[c] + sum(th * col[c] for th, col in zip(theta, columns)) for c in CHANNELS}
    return theta, out


def base_residuals(bfit: BodyFit, sensor: str) -> dict:
    """`residuals_with(bfit, sensor)` (the sensor's residuals for its own measurements), computed once per fit
    and sensor: every (BE1) column is a difference against it (soft_tissue asks for it per (f_n, ζ) grid point
    against a refit θ*). Cached in bfit.info, keyed by the identity of the sensor's fit and measurements, so a
    changed SensorFit or session recomputes it."""
    from imugraph.diagnose.body.fit import residuals_with

    cache = bfit.info.setdefault("_base_residuals", {})
    sf, ses = bfit.sensors[sensor], bfit.session.sensors[sensor]
    hit = cache.get(sensor)
    if hit is None or hit[0] is not sf or hit[1] is not ses:
        hit = cache[sensor] = (sf, ses, residuals_with(bfit, sensor))
    return hit[2]


def changed_columns(bfit: BodyFit, sensor: str, deltas: list, kind: str, key=None) -> list:
    """(BE1) columns for measurement changes `deltas` (list of (N, 3)) of the gyro (kind "gyr", first order by a
    small step) or the accelerometer ("acc", exact: linear). key: cache them in bfit.info under this key (the
    folds of one effect share them: they do not depend on the training rows)."""
    from imugraph.diagnose.body.fit import residuals_with

    cache = bfit.info.setdefault("_columns", {})
    if key is not None and (key, sensor) in cache:
        return cache[(key, sensor)]

    ses = bfit.session.sensors[sensor]
    base = base_residuals(bfit, sensor)
    cols = []
    for d in deltas:
        eps = 1e-3 / max(float(np.max(np.abs(d))), 1e-12) if kind == "gyr" else 1.0
        r = residuals_with(bfit, sensor, gyr=ses.gyr + eps * d) if kind == "gyr" else \
            residuals_with(bfit, sensor, acc=ses.acc + d)
        cols.append({c: (r[c] - base[c]) / eps for c in CHANNELS})
    if key is not None:
        cache[(key, sensor)] = cols
    return cols
