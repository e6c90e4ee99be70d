"""Streaming a simulated session through one end-of-stream extension at a time (shared by the tests; not a test
module)."""

from __future__ import annotations

import numpy as np

from imugraph.evaluate import orientation_error
from imugraph.graphs.stream import StreamOptions, StreamSmoother

# the end-of-stream extensions off (each is on by default since session 18): a test turns on the one it checks
EXTENSIONS_OFF = {"windows_end": False, "velocity_end": "off", "gyro_map_end": False}


def stream_isolated(session, cal, **opt):
    """(smoother, filtered (N, 4)) of `session` pushed sample by sample through full iSAM2 (lag_s None) from `cal`,
    with the end extensions off except what `opt` sets; `finish` called."""
    sm = StreamSmoother(cal, session.rate, StreamOptions(**{"lag_s": None, **EXTENSIONS_OFF, **opt}),
                        g0=float(np.median(np.linalg.norm(session.acc, axis=1))))
    q = np.array([sm.push(session.t[i], session.gyr[i], session.acc[i], session.mag[i]) for i in range(session.n)])
    sm.finish()
    return sm, q


def truth_rms(q, session) -> float:
    """RMS angle (°) of q against the session's true orientation, no heading offset, no time shift."""
    return orientation_error(q, session.quat, None, session.rate, heading=False, max_shift=0.0).rms_deg
