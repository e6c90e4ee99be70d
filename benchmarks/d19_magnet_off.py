"""Issue 3, session 19 (the lead's check of helper D's `mag_delay_end`): the end-of-stream lag estimate on a simulated
session whose start calibration holds an attached magnet that comes off at 14 s (imugraph.sim.scenario.
magnet_comes_off_session: 50 Hz, true lag 0), full iSAM2 with every default, with mag_delay_end off / True / "clean" / "guarded"
(helper G: the end graph decides between the shifts).
Prints the lag the end graph estimated and the smoothed error against the simulation's truth.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/d19_magnet_off.py
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.stream_vs_batch import stream_with_recorder  # noqa: E402
from benchmarks._usage import no_arguments  # noqa: E402


def main() -> int:
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.stream import StreamOptions
    from imugraph.sim.scenario import magnet_comes_off_session

    s, start, _ = magnet_comes_off_session()
    print(f"rate {s.rate:.0f} Hz, start lag {1e3 * start.mag_delay_s:.1f} ms")
    for mode in (False, True, "clean", "guarded"):   # "guarded": session 19, helper G
        r, sm = stream_with_recorder(s, StreamOptions(lag_s=None, mag_delay_end=mode), 10.0, start, 0)
        info = sm._delay_end.info if getattr(sm, "_delay_end", None) is not None else {}
        err = orientation_error(r.smoothed, s.quat, None, s.rate).rms_deg
        lag = f"τ̂ {1e3 * info['tau_s']:.1f} ms, shift {info['shift_start']} → {info['shift_end']}" if info else "—"
        guard = (f"; guard F(s₀) {info['guard_cost_s0']:.2f} vs F(s₁) {info['guard_cost_s1']:.2f}, magnetometer "
                 f"{info['guard_mag_s0']:.2f} vs {info['guard_mag_s1']:.2f}, applied {info['applied']}"
                 if "guard_cost_s0" in info else "")
        print(f"mag_delay_end={mode!r}: {lag}{guard}; smoothed vs truth {err:.3f}°; delay_end CPU "
              f"{info.get('cpu_s', 0.0):.2f} s")
    return 0


if __name__ == "__main__":
    no_arguments(__doc__)          # sys.argv: --help, or no arguments at all
    sys.exit(main())
