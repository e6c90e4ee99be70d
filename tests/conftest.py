"""Shared fixtures: the real-data folder (skipping when absent) and small synthetic sessions."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from imugraph.config import data_dir as _data_dir
from imugraph.geometry import expmap, logmap, rotmat_to_quat
from imugraph.io.session import Session

G = 9.80665


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared recordings folder; skips the test when it is absent."""
    root = _data_dir()
    if not root.is_dir():
        pytest.skip(f"shared data folder {root} is absent")
    return root


@pytest.fixture(scope="session")
def data_file(data_dir: Path) -> Callable[[str], Path]:
    """Factory: path of a file under the data folder, skipping the test when it is missing."""
    def get(rel: str) -> Path:
        p = data_dir / rel
        if not p.exists():
            pytest.skip(f"{p} is absent")
        return p
    return get


def synthetic_session(n: int = 2000, rate: float = 100.0, peak_rate: float = 0.5, seed: int = 0) -> Session:
    """A smooth, noisy 9-axis session with known truth (nRb, z up, field dip 60°, 50 µT).

    Orientation: rotation vector r(t) with slow sinusoids per axis, nRb = Exp(r(t)); the gyro is the
    exact body rate between samples, ω_k = Log(nRb_kᵀ·nRb_{k+1})/dt, so integrating it reproduces
    nRb. Accelerometer b_acc = bRn·[0, 0, g] + noise; magnetometer b_mag = 50·bRn·n_mag + noise.

    Args:
        n: samples.  rate: Hz.  peak_rate: approximate peak angular rate in rad/s.  seed: RNG seed.
    Returns:
        Session with quat truth.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    freqs = np.array([0.11, 0.07, 0.05])
    amp = peak_rate / (2 * np.pi * freqs) / np.sqrt(3)
    r = amp * np.sin(2 * np.pi * freqs * t[:, None] + np.array([0.0, 1.0, 2.0]))
    nRb = expmap(r)
    gyr = np.empty((n, 3))
    gyr[:-1] = logmap(np.einsum("nji,njk->nik", nRb[:-1], nRb[1:])) * rate
    gyr[-1] = gyr[-2]
    dip = np.deg2rad(60.0)
    n_mag = 50.0 * np.array([np.cos(dip), 0.0, -np.sin(dip)])
    acc = np.einsum("nji,j->ni", nRb, np.array([0.0, 0.0, G])) + 0.05 * rng.standard_normal((n, 3))
    mag = np.einsum("nji,j->ni", nRb, n_mag) + 0.3 * rng.standard_normal((n, 3))
    gyr = gyr + 0.005 * rng.standard_normal((n, 3))
    return Session(t=t, gyr=gyr, acc=acc, mag=mag, quat=rotmat_to_quat(nRb), source="<synthetic>",
                   name="synthetic", meta={})


@pytest.fixture(scope="session")
def valid_session() -> Session:
    """A 20 s, 100 Hz synthetic session that passes validation (slow rotation, ≤ ~0.5 rad/s)."""
    return synthetic_session()


@pytest.fixture(scope="session")
def make_session() -> Callable[..., Session]:
    """Factory for synthetic sessions: make_session(n=…, rate=…, peak_rate=…, seed=…)."""
    return synthetic_session


@pytest.fixture(scope="session")
def assert_block_gradient() -> Callable:
    """Check of a Python block (linearize / cost): the gradient in its linearisation, −(augmented Hessian's
    last column), equals the central-difference gradient of its cost over key_list (Rot3 keys 'r' perturbed
    on the manifold by retract, vector keys additively)."""
    import gtsam

    def check(block, values, key_list, h: float = 1e-6, rtol: float = 1e-5, atol: float = 1e-6) -> None:
        H = block.linearize(values).augmentedHessian(gtsam.Ordering(key_list))
        grad, num = -H[:-1, -1], []
        for key in key_list:
            is_rot = gtsam.Symbol(key).chr() == ord("r")
            x = values.atRot3(key) if is_rot else values.atVector(key)
            for i in range(3 if is_rot else len(x)):
                d = np.zeros(3 if is_rot else len(x))
                d[i] = h
                p, m = gtsam.Values(values), gtsam.Values(values)
                p.update(key, x.retract(d) if is_rot else x + d)
                m.update(key, x.retract(-d) if is_rot else x - d)
                num.append((block.cost(p) - block.cost(m)) / (2 * h))
        np.testing.assert_allclose(grad, num, rtol=rtol, atol=atol)

    return check


@pytest.fixture(scope="session")
def feed_stream() -> Callable:
    """Feed every sample of a session to a StreamSmoother in order; every `every`-th sample (1-based count)
    record probe(smoother). Returns the recorded values (empty without a probe)."""
    def feed(sm, session: Session, every: int = 0, probe: Callable | None = None) -> list:
        seen = []
        for i in range(session.n):
            sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i])
            if probe is not None and every and i % every == every - 1:
                seen.append(probe(sm))
        return seen

    return feed
