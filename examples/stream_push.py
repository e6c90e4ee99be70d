"""Push samples into imugraph's incremental smoother from your own acquisition loop.

    .venv/bin/python examples/stream_push.py

A calibration is needed first: here from a short batch bootstrap on the first 20 s (in a real setup: a
calibration.json from `imugraph calibrate`, read with imugraph.io.writers.read_calibration_json). The
acquisition loop is simulated by iterating over a simulated session; replace `acquire()` with your driver.
Each `push` returns at once the filtered orientation (w, x, y, z, sensor → nav) for that sample; pass
mag=None when the magnetometer has no new sample (lower rate). `finish()` then `smoothed()` give the
smoothed orientation of every accepted sample (rows at `sample_times()`). The calibration (D, o, dip) is
re-estimated online from the bootstrap start — by default (StreamOptions.calib_states) as a state of the graph
that every magnetometer factor shares: no refit is ever "applied" to the filtered output (it keeps the start
calibration; `applied` is False in every history row), `smoother.cal` stays the start calibration until `finish()`
and is the streamed estimate after it (what `imugraph stream` writes to calibration.json).
`smoother.calibration_history` holds one row per refit, a record of that estimate (t, D, o, dip_deg, std,
applied), for a convergence plot. (With StreamOptions(calib_states=False) the closed-form refits instead swap in when well
determined: then `smoother.cal` is the latest one applied, and `applied` says which.)
`imugraph stream SESSION --out OUT` writes the same rows to OUT/calibration_history.json;
`examples/plot_convergence.py OUT [--batch calibration.json]` draws them.
"""

import numpy as np

from imugraph.graphs.stream import StreamOptions, StreamSmoother
from imugraph.graphs.stream_run import bootstrap_calibration
from imugraph.sim.scenario import distorted_session

session, _ = distorted_session(seed=7, duration_s=60.0, rate_hz=100.0)


def acquire():
    """Stand-in for a sensor driver: yields (t, gyr rad/s, acc m/s², mag or None)."""
    for i in range(session.n):
        yield session.t[i], session.gyr[i], session.acc[i], (session.mag[i] if i % 4 == 0 else None)


cal, n_boot = bootstrap_calibration(session, bootstrap_s=20.0)   # or read_calibration_json("calibration.json")
smoother = StreamSmoother(cal, rate=100.0, options=StreamOptions(lag_s=2.0))   # lag_s=None: full iSAM2
for i, (t, gyr, acc, mag) in enumerate(acquire()):
    q_now = smoother.push(t, gyr, acc, mag)          # filtered nRb available now
    if i % 1000 == 0:
        print(f"t = {t:5.1f} s  q = {np.round(q_now, 3)}")
smoother.finish()
q_smoothed = smoother.smoothed()
st = smoother.stats           # keyframe updates, and the periodic work done on samples between keyframes
print(f"{st.accepted} samples, {len(st.update_s)} updates, p99 update {1e3 * np.percentile(st.update_s, 99):.2f} ms, "
      f"p99 between keyframes {1e3 * np.percentile(st.between_s, 99):.2f} ms; counts {st.counts()}")
hist = smoother.calibration_history
if hist:
    last = hist[-1]
    print(f"{len(hist)} calibration refits ({sum(r['applied'] for r in hist)} applied); last at t = {last['t']:.1f} s: "
          f"o = {np.round(last['o'], 3)} ± {np.round(last['std']['o'], 3) if last['std'] else '—'}")
print(f"start o = {np.round(cal.o, 3)}; smoother.cal.o after finish() = {np.round(smoother.cal.o, 3)} (the streamed one)")
