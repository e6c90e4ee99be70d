"""`imugraph simulate`: write a simulated session in the NPZ session contract (DESIGN.md).

Keys: `gyr` (N, 3) rad/s, `acc` (N, 3) m/s², `mag` (N, 3) (field norm 50, µT-like), `t` (N,) s, `quat`
(N, 4) true nRb w,x,y,z. The truth that generated it is stored in extra keys, which readers ignore:
`true_D` (3, 3), `true_o` (3,), `true_dip_deg` (), `true_gyro_bias` (3,) rad/s, `seed` ().
The file is written atomically (temporary file in the same folder, then rename).

`--out FILE.csv` writes the imugraph CSV instead (docs/formats.md: t, gyr_x…z, acc_x…z, mag_x…z, quat_w…z; no
truth keys); any other extension of a session format (.mat, .hdf5, .txt, .json) is refused (it used to get
an NPZ zip under that name). `--effect NAME` (repeatable, or comma-separated) adds an unmodelled effect of the
diagnosis library to the simulated session (`imugraph.diagnose.effects.EFFECTS[NAME].inject`, rng seeded from
--seed); what was injected is stored in the NPZ key `effects` (a JSON text: name → the effect's truth).
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
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return _write_atomic(path, buffer.getvalue(), "FILE.npz")


def _write_atomic(path: Path, data: bytes, kind: str) -> Path:
    """`imugraph.io.writers.atomic_write_bytes`, an OSError as SessionError field 'out' (kind: "FILE.npz", ...)."""
    from imugraph.io.writers import atomic_write_bytes

    try:
        return atomic_write_bytes(path, data)
    except OSError as exc:
        raise SessionError(str(path), "out", f"a location that cannot be written ({exc.strerror or exc})",
                           f"a writable file path (--out {kind})") from None


CSV_COLUMNS = ("t", "gyr_x", "gyr_y", "gyr_z", "acc_x", "acc_y", "acc_z", "mag_x", "mag_y", "mag_z",
               "quat_w", "quat_x", "quat_y", "quat_z")
REFUSED_SUFFIXES = (".mat", ".hdf5", ".h5", ".txt", ".json", ".mvnx")


def save_csv_atomic(path: Path, session) -> Path:
    """The imugraph CSV (CSV_COLUMNS, '%.17g': every float64 read back exactly; 'nan' where no sample), atomic.

    Raises:
        SessionError: the location cannot be written (field 'out').
    """
    table = np.column_stack([session.t, session.gyr, session.acc, session.mag, session.quat])
    buffer = io.StringIO()
    np.savetxt(buffer, table, fmt="%.17g", delimiter=",", header=",".join(CSV_COLUMNS), comments="")
    return _write_atomic(path, buffer.getvalue().encode("utf-8"), "FILE.csv")


def effect_names(values) -> list[str]:
    """--effect values (repeatable, comma-separated) as a list of names, each checked against EFFECTS.

    Raises:
        SessionError: an unknown name (field 'effect').
    """
    from imugraph.diagnose.effects import EFFECTS

    names = [n.strip() for v in (values or []) for n in str(v).split(",") if n.strip()]
    bad = [n for n in names if n not in EFFECTS]
    if bad:
        raise SessionError("--effect", "effect", ", ".join(bad), f"names among {', '.join(sorted(EFFECTS))}")
    return names


def inject_effects(session, names: list[str], seed: int):
    """`session` with each named effect injected in turn (EFFECTS[name].inject, one rng seeded (seed, 1)).

    Returns:
        (session, {name: the effect's truth (params, t_start, t_end)}).
    """
    from imugraph.diagnose.effects import EFFECTS

    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 1])   # not the simulation's own stream
    truths = {}
    for name in names:
        session, truths[name] = EFFECTS[name].inject(session, rng)
    return session, truths


def run_simulate(args: argparse.Namespace) -> int:
    """simulate --out FILE.npz|FILE.csv [--seed N] [--duration S] [--rate HZ] [--effect NAME …] [--quiet].

    Returns:
        0 on success (errors are raised as ImugraphError and reported by `imugraph.cli.main`).
    """
    from imugraph.io.writers import json_ready
    from imugraph.sim.scenario import distorted_session

    import json

    progress = common.Progress(args.quiet)
    out = Path(args.out).expanduser()
    if out.is_dir():
        raise SessionError(str(out), "out", "an existing folder", "a file path such as session.npz")
    suffix = out.suffix.lower()
    if suffix in REFUSED_SUFFIXES:
        raise SessionError(str(out), "out", f"extension {out.suffix}", "FILE.npz (the session and its truth) or "
                           "FILE.csv (the imugraph CSV columns)")
    names = effect_names(getattr(args, "effect", None))
    progress.say(f"simulating {args.duration:g} s at {args.rate:g} Hz (seed {args.seed})")
    session, truth = distorted_session(args.seed, args.duration, args.rate)
    injected = {}
    if names:
        progress.say(f"injecting {', '.join(names)}")
        session, injected = inject_effects(session, names, args.seed)
    if suffix == ".csv":
        save_csv_atomic(out, session)
    else:
        extra = {"effects": np.array(json.dumps(json_ready(injected)))} if injected else {}
        save_npz_atomic(out, {
            "gyr": session.gyr, "acc": session.acc, "mag": session.mag, "t": session.t, "quat": session.quat,
            "true_D": truth.D, "true_o": truth.o, "true_dip_deg": np.float64(truth.dip_deg),
            "true_gyro_bias": truth.gyro_bias, "seed": np.int64(args.seed), **extra,
        })
    print(f"wrote {out}: {session.n} samples, {args.duration:g} s at {args.rate:g} Hz, seed {args.seed}, "
          f"dip {truth.dip_deg:.2f}°" + (f", effects {', '.join(names)}" if names else ""))
    return 0
