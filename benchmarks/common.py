"""Shared helpers of the benchmarks: BROAD trials, their groups, a plain text table and peak memory.

The BROAD trials are read from `imugraph.config.broad_dir()` ($IMUGRAPH_DATA/broad, else
../shared/data/broad); nothing is copied into the repository.
"""

from __future__ import annotations

import json
import re
import resource
import sys
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from imugraph.config import broad_dir
from imugraph.errors import SessionError
from imugraph.io.session import Session

_BROAD_FIELDS = ("imu_gyr", "imu_acc", "imu_mag", "sampling_rate", "opt_quat", "movement")


def _load_mat(path: Path) -> Session:
    """Fallback BROAD .mat reader (scipy) used when imugraph.io.readers is not available."""
    from scipy.io import loadmat

    try:
        mat = loadmat(str(path))
    except (OSError, ValueError) as exc:
        raise SessionError(str(path), "<file>", f"an unreadable file ({exc})", "a MATLAB .mat file") from exc
    missing = [k for k in _BROAD_FIELDS if k not in mat]
    if missing:
        raise SessionError(str(path), missing[0], "no such variable", f"BROAD variables {_BROAD_FIELDS}")
    rate = float(np.asarray(mat["sampling_rate"]).ravel()[0])
    gyr = np.asarray(mat["imu_gyr"], float)
    n = gyr.shape[0]
    return Session(
        t=np.arange(n) / rate, gyr=gyr, acc=np.asarray(mat["imu_acc"], float),
        mag=np.asarray(mat["imu_mag"], float), quat=np.asarray(mat["opt_quat"], float),
        movement=np.asarray(mat["movement"]).reshape(-1).astype(bool),
        source=str(path), name=path.stem, meta={"rate": rate, "reader": "benchmarks.common"},
    )


def load_broad_trial(path: str | Path) -> Session:
    """Read one BROAD trial as a Session (mag in µT, quat = opt_quat, movement mask).

    Uses `imugraph.io.readers.load_session` when that module exists, else a scipy reader here.

    Args:
        path: a BROAD .mat (or, with the imugraph reader, .hdf5) file.

    Returns:
        Session with t (N,) s, gyr (N, 3) rad/s, acc (N, 3) m/s², mag (N, 3) µT, quat (N, 4) w,x,y,z
        sensor→ENU (NaN where tracking dropped), movement (N,) bool.

    Raises:
        SessionError: unreadable file or missing BROAD variable.
    """
    path = Path(path)
    try:
        from imugraph.io.readers import load_session
    except ImportError:
        return _load_mat(path)
    return load_session(path)


def broad_trials(root: Path | None = None) -> list[Path]:
    """The BROAD .mat trials present, sorted by name (17 in ../shared/data/broad).

    Args:
        root: folder to list; default `imugraph.config.broad_dir()`.

    Returns:
        Sorted list of paths (empty when the folder is absent).
    """
    root = broad_dir() if root is None else Path(root)
    return sorted(root.glob("[0-9][0-9]_*.mat")) if root.is_dir() else []


def trial_number(path: str | Path) -> int:
    """The BROAD trial number from a file name such as 06_undisturbed_fast_rotation_A.mat → 6."""
    m = re.match(r"(\d+)_", Path(path).name)
    if m is None:
        raise SessionError(str(path), "<file name>", f"'{Path(path).name}'", "a name starting with NN_")
    return int(m.group(1))


def select_trials(spec: str) -> list[Path]:
    """The BROAD trials named by a command line's "all" or "1,6,34" (numbers), in file order."""
    paths = broad_trials()
    if spec != "all":
        want = {int(x) for x in spec.split(",")}
        paths = [p for p in paths if trial_number(p) in want]
    return paths


def parse_variants(argv: Sequence[str]) -> tuple[dict, list]:
    """`--variant "A=1;B=2"` (repeatable) out of argv: ({"base": [], "A=1;B=2": ["A=1", "B=2"], …}, the other
    arguments in order). Each variant's items are `parse_options` strings."""
    variants, rest, i = {"base": []}, [], 0
    while i < len(argv):
        if argv[i] == "--variant":
            variants[argv[i + 1]] = [x for x in argv[i + 1].split(";") if x]
            i += 2
        else:
            rest.append(argv[i])
            i += 1
    return variants, rest


def trial_groups(root: Path | None = None) -> dict[str, list[int]]:
    """Map each BROAD group name (undisturbed, disturbed, rotation, fast, ...) to its trial numbers.

    Read from trials.json beside the trials; includes trials that are listed but not present.

    Args:
        root: BROAD folder; default `imugraph.config.broad_dir()`.

    Returns:
        {group name: sorted trial numbers}; empty when trials.json is absent.
    """
    root = broad_dir() if root is None else Path(root)
    meta_path = root / "trials.json"
    if not meta_path.is_file():
        return {}
    trials = json.loads(meta_path.read_text())["trials"]
    groups: dict[str, list[int]] = {}
    for name, info in trials.items():
        for g in info["groups"]:
            groups.setdefault(g, []).append(trial_number(name))
    return {g: sorted(v) for g, v in groups.items()}


def groups_of(path: str | Path, root: Path | None = None) -> list[str]:
    """The group names a trial file belongs to (e.g. ['all_trials', 'undisturbed', 'rotation', ...])."""
    k = trial_number(path)
    return [g for g, nums in trial_groups(root).items() if k in nums]


def _fmt(v: Any) -> str:
    if isinstance(v, (float, np.floating)):
        return f"{v:.3g}" if abs(v) >= 1e4 or (v != 0 and abs(v) < 1e-2) else f"{v:.2f}"
    return str(v)


def print_table(rows: Sequence[dict[str, Any]] | Sequence[Sequence[Any]], columns: Sequence[str],
                file=None) -> str:
    """Print a plain aligned text table and return it.

    Args:
        rows: dicts keyed by column name, or sequences in column order.
        columns: column headers.
        file: stream to print to (default stdout).

    Returns:
        The table text.
    """
    cells = [[_fmt(r.get(c, "")) for c in columns] if isinstance(r, dict) else [_fmt(v) for v in r]
             for r in rows]
    widths = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(columns)]

    def line(vals: Iterable[str]) -> str:
        return "  ".join(v.rjust(w) if i else v.ljust(w) for i, (v, w) in enumerate(zip(vals, widths)))

    out = "\n".join([line(columns), line("-" * w for w in widths)] + [line(r) for r in cells])
    print(out, file=file or sys.stdout)
    return out


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, MB (ru_maxrss: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


def finite_mean(rows: Sequence[dict], key: str) -> float:
    """Mean of rows[i][key] over the rows that have a finite value (NaN when none has)."""
    vals = [r[key] for r in rows if key in r and np.isfinite(r[key])]
    return float(np.mean(vals)) if vals else float("nan")


def option_overrides(values: Sequence[str] | None, cls: type) -> dict:
    """{FIELD: value} from `FIELD=VALUE` strings (VALUE a Python literal) for the options dataclass `cls`
    (calibration Options, StreamOptions, ...); an unknown field or a missing `=` fails with the known fields."""
    import ast
    from dataclasses import fields as dc_fields

    known = {f.name for f in dc_fields(cls)}
    kw = {}
    for item in values or []:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in known:
            raise SystemExit(f"--opt {item!r}: expected FIELD=VALUE with FIELD one of {sorted(known)}")
        kw[name] = ast.literal_eval(value)
    return kw


def parse_options(values: Sequence[str] | None, **fixed: Any):
    """Options of imugraph.calibration.ml from `--opt FIELD=VALUE` strings (VALUE a Python literal), e.g.
    `field_sigma=(0.015,0.003,0.015)`; unknown fields fail with the list of known ones."""
    from imugraph.calibration.ml import Options

    return Options(**{**fixed, **option_overrides(values, Options)})


def stream_overrides(values: Sequence[str] | None) -> dict:
    """StreamOptions fields from `--opt FIELD=VALUE` strings (as `option_overrides`), e.g. `position_sigma=0.3`."""
    from imugraph.graphs.stream_options import StreamOptions

    return option_overrides(values, StreamOptions)


def pop_opts(argv: list[str]) -> tuple[list[str], list[str]]:
    """Split `--opt FIELD=VALUE` pairs out of argv: (the FIELD=VALUE strings, the rest of argv)."""
    opts, rest, i = [], [], 0
    while i < len(argv):
        if argv[i] == "--opt" and i + 1 < len(argv):
            opts.append(argv[i + 1])
            i += 2
        else:
            rest.append(argv[i])
            i += 1
    return opts, rest


def pop_value(argv: list[str], flag: str, default: str) -> tuple[str, list[str]]:
    """Take `flag VALUE` out of argv: (VALUE or default, the rest of argv)."""
    if flag in argv:
        i = argv.index(flag)
        return argv[i + 1], argv[:i] + argv[i + 2:]
    return default, argv


def iter_broad(select: set[str] | None = None):
    """(two-digit trial number, session, movement mask) of every BROAD trial, or of those in select."""
    for path in broad_trials():
        num = path.name[:2]
        if select and num not in select:
            continue
        s = load_broad_trial(path)
        yield num, s, s.movement.astype(bool)


def error_parts(q, s: Session, mask) -> tuple[float, float, float]:
    """Total, inclination and heading RMS error (deg) of q against the session's reference quat."""
    from imugraph.evaluate import heading_error, inclination_error, orientation_error

    return tuple(f(q, s.quat, mask, s.rate).rms_deg for f in (orientation_error, inclination_error, heading_error))


BOOT_BLOCK_S, N_BOOT = 10.0, 2000


def rms_diff_ci(q_a: np.ndarray, q_b: np.ndarray, q_ref: np.ndarray, mask, rate: float) -> list[float]:
    """95 % moving-block-bootstrap interval (degrees) of RMS_a − RMS_b over the samples both systems score.

    Squared errors e²_a, e²_b per scored sample, each system at its own best shift and heading (as
    `orientation_error`); nb = ⌈K/L⌉ blocks of L = BOOT_BLOCK_S seconds drawn with replacement (block sums from
    a cumulative sum); percentiles 2.5 and 97.5 of √(Σe²_a/(nb L)) − √(Σe²_b/(nb L)) over N_BOOT resamples,
    seed 0. Evaluation only: the reference is resampled, nothing is refitted. Errors correlated over longer
    than a block make the interval too narrow, never too wide."""
    from imugraph.evaluate import orientation_error_series

    ia, ea = orientation_error_series(q_a, q_ref, mask)
    ib, eb = orientation_error_series(q_b, q_ref, mask)
    _, ja, jb = np.intersect1d(ia, ib, return_indices=True)
    n, L = ja.size, max(1, int(round(BOOT_BLOCK_S * rate)))
    L = min(L, n)
    block = [np.convolve(e[j] ** 2, np.ones(L), "valid") for e, j in ((ea, ja), (eb, jb))]   # sums over L samples
    starts = np.random.default_rng(0).integers(0, n - L + 1, size=(N_BOOT, -(-n // L)))
    d = np.sqrt(block[0][starts].sum(1) / starts.shape[1] / L) - np.sqrt(block[1][starts].sum(1) / starts.shape[1] / L)
    return [round(float(v), 4) for v in np.percentile(d, [2.5, 97.5])]


def print_variant_summary(rows: Sequence[dict], script: str, arg: str, opts: Any, note: str = "") -> tuple | None:
    """The closing lines of a base-vs-variant benchmark (rows with "trial", "base", "variant", "diff"):
    the table, the two means and the largest increase. Returns (mean base, mean variant), or None (and a
    message naming `arg`) when no trial was selected."""
    if not rows:
        print(f"{script}: no BROAD trial matches {arg!r}", file=sys.stderr)
        return None
    print_table(rows, list(rows[0].keys()))
    m0, m1 = float(np.mean([r["base"] for r in rows])), float(np.mean([r["variant"] for r in rows]))
    worst = max(rows, key=lambda r: r["diff"])
    print(f"mean: base {m0:.3f}°, variant {m1:.3f}°; largest increase {worst['diff']:+.3f}° ({worst['trial']}); "
          f"variant options: {opts}{note}")
    return m0, m1


def rows_by_trial_config(names: Sequence[str], only: Sequence[str] | None = None) -> dict:
    """{(trial, config): row} from bench_out JSON files written by stream_vs_batch-style runs (`rows` with `trial`
    and `config`); a later file's row wins; `only`: keep these configs."""
    from benchmarks.output import OUT_DIR

    best: dict = {}
    for n in names:
        for r in json.loads((OUT_DIR / n).read_text())["rows"]:
            if only is None or r["config"] in only:
                best[(r["trial"], r["config"])] = r
    return best


def print_config_means(best: dict, configs: Sequence[str]) -> None:
    """Per config, over the trials every config has: the mean of vs_batch_field_h_deg, how many ≤ 0.1°, and the mean
    of stream_truth_deg."""
    trials = sorted({t for t, _ in best})
    common = [t for t in trials if all((t, c) in best for c in configs)]
    for c in configs:
        v = np.array([best[(t, c)]["vs_batch_field_h_deg"] for t in common])
        tr = np.array([best[(t, c)]["stream_truth_deg"] for t in common])
        print(f"{c} over {len(common)} trials: vs_batch_field_h mean {v.mean():.3f}°, ≤ 0.1°: {int((v <= 0.1).sum())}/"
              f"{len(common)}; truth mean {tr.mean():.3f}°")


def stream_variant_parser(doc: str, trials: str, config: str, out: str):
    """The argparse parser shared by the stream_vs_batch wrappers (v18_velocity_end, y19_noise_end): TRIALS, --config,
    --cache, --bootstrap-s, --out, --summarise (callers add their own flags)."""
    import argparse

    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("trials", nargs="?", default=trials)
    ap.add_argument("--config", default=config)
    ap.add_argument("--cache", default="/tmp/A_cache")
    ap.add_argument("--bootstrap-s", type=float, default=30.0)
    ap.add_argument("--out", default=out)
    ap.add_argument("--summarise", default=None, help="comma-separated bench_out JSONs of earlier runs: per-trial table "
                    "(the last row per trial and config) and per-config means over the trials every config has; no run")
    return ap


def print_run_means(rows: Sequence[dict], configs: Sequence[str]) -> None:
    """Per config, over this run's rows: the mean of vs_batch_field_h_deg, how many ≤ 0.1°, the mean of
    stream_truth_deg."""
    for c in configs:
        sub = [r for r in rows if r["config"] == c]
        v = np.array([r["vs_batch_field_h_deg"] for r in sub])
        tr = np.array([r["stream_truth_deg"] for r in sub])
        if v.size:
            print(f"{c}: vs_batch_field_h mean {v.mean():.3f}°, ≤ 0.1°: {int((v <= 0.1).sum())}/{v.size}; "
                  f"truth mean {tr.mean():.3f}°")


def stream_row_line(r: dict, width: int, middle: str) -> str:
    """One printed row of the stream_vs_batch wrappers: trial, config, the stream vs the batch (heading-aligned),
    vs the same model and vs the truth, then `middle` (the wrapper's own columns), the stream's CPU and the load."""
    import os

    return (f"{r['trial']} {r['config']:{width}s} vs_batch_field_h {r['vs_batch_field_h_deg']:.3f}° same "
            f"{r['same_deg']:.3f}° truth {r['stream_truth_deg']:.3f}° (batch {r['batch_field_truth_deg']:.3f}°) | "
            f"{middle} stream cpu {r['stream_cpu_s']:.1f} s | load {os.getloadavg()[0]:.1f}")
