"""`imugraph simulate`: write a simulated session in the NPZ session contract (DESIGN.md).

Keys: `gyr` (N, 3) rad/s, `acc` (N, 3) m/s², `mag` (N, 3) (field norm 50, µT-like), `t` (N,) s, `quat`
(N, 4) true nRb w,x,y,z. The truth that generated it is stored in extra keys, which readers ignore:
`true_D` (3, 3), `true_o` (3,), `true_dip_deg` (), `true_gyro_bias` (3,) rad/s, `seed` ().
The file is written atomically (temporary file in the same folder, then rename).
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np

from imugraph.commands import common
from imugraph.errors import SessionError


def save_npz_atomic(path: Path, arrays: dict) -> Path:
    """np.savez_compressed in memory, then written atomically (`imugraph.io.writers.atomic_write_bytes`).

    Args:
        path: destination file (any name; no '.npz' is appended).
        arrays: name → array.

    Returns:
        The destination path.

    Raises:
        SessionError: the location cannot be written (field 'out').
    """
    from imugraph.io.writers import atomic_write_bytes

    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    try:
        return atomic_write_bytes(path, buffer.getvalue())
    except OSError as exc:
        raise SessionError(str(path), "out", f"a location that cannot be written ({exc.strerror or exc})",
                           "a writable file path (--out FILE.npz)") from None


def run_simulate(args: argparse.Namespace) -> int:
    """simulate --out FILE.npz [--seed N] [--duration S] [--rate HZ] [--quiet].

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    from imugraph.sim.scenario import distorted_session

    progress = common.Progress(args.quiet)
    out = Path(args.out).expanduser()
    if out.is_dir():
        raise SessionError(str(out), "out", "an existing folder", "a file path such as session.npz")
    progress.say(f"simulating {args.duration:g} s at {args.rate:g} Hz (seed {args.seed})")
    session, truth = distorted_session(args.seed, args.duration, args.rate)
    save_npz_atomic(out, {
        "gyr": session.gyr, "acc": session.acc, "mag": session.mag, "t": session.t, "quat": session.quat,
        "true_D": truth.D, "true_o": truth.o, "true_dip_deg": np.float64(truth.dip_deg),
        "true_gyro_bias": truth.gyro_bias, "seed": np.int64(args.seed),
    })
    print(f"wrote {out}: {session.n} samples, {args.duration:g} s at {args.rate:g} Hz, seed {args.seed}, "
          f"dip {truth.dip_deg:.2f}°")
    return 0
