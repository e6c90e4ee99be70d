"""Many sessions on Dask (`dask.distributed`): calibration and smoothing of each one, in parallel.

    from imugraph.batch import run_batch
    rows = run_batch(["a.npz", "b.mat"], "batch_out", workers=2)      # local cluster of 2 processes

Graphs with Python factors cannot be pickled, so nothing but the session PATH, its output folder and
plain options travel to a worker: `run_one` reads the session there, builds its own graph and writes
DIR/<name>/ (`path_names`: the stem, or the shortest distinguishing path suffix) with the files of
`imugraph calibrate` (through the same function, `imugraph.commands.calibrate.calibrate_path`). It never
raises: a failure comes back as a row with status "failed" and the error on one line, and does not stop the
other sessions.

The default cluster is a `distributed.LocalCluster` of worker processes (processes=True,
threads_per_worker=1); `scheduler="tcp://host:8786"` uses an existing cluster instead (its workers must
see the session paths and the output folder, e.g. on a shared file system).
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import logging
import math
import os
import sys
import time
from pathlib import Path
from typing import Iterator, Optional, Sequence, Union

from imugraph.commands.calibrate import CalibrateOptions
from imugraph.errors import ImugraphError, SessionError

PathLike = Union[str, Path]
# summary.csv columns (summary.json rows carry the same keys, plus the calibrate figures when ok)
COLUMNS = ("session", "status", "time_s", "error_deg", "out", "path", "error")
MAX_ERROR_CHARS = 300
# what `run_one` (calibrate_path → commands.common.write_estimate) writes into a session's folder
SESSION_FILES = ("calibration.json", "orientation.npz", "calibration.png", "heading.png")


def one_line(exc: BaseException) -> str:
    """An exception as one short line: our own errors as they are, others prefixed by their type."""
    if isinstance(exc, ImugraphError):
        text = str(exc)
    elif isinstance(exc, OSError) and exc.strerror:
        text = f"{exc.filename + ': ' if exc.filename else ''}{exc.strerror}"
    else:
        text = f"{type(exc).__name__}: {exc}"
    text = " ".join(text.split())          # gtsam errors can print whole graphs over many lines
    return text if len(text) <= MAX_ERROR_CHARS else text[:MAX_ERROR_CHARS - 1] + "…"


def output_folders(paths: Sequence[PathLike], out: PathLike, naming: str = "numbered") -> list[Path]:
    """One output folder per session under `out`.

    naming "numbered" (the API's default before U23): DIR/<session stem>, a stem seen before gets _2, _3, … in the
    order given (trial.mat in two folders: which one is `trial` depends on the order). naming "path" (what
    `run_batch` and `imugraph batch` use): the shortest distinguishing path suffix (`path_names`), the same for a
    session whatever the order of the others.
    """
    if naming == "path":
        return [Path(out) / name for name in path_names(paths)]
    if naming != "numbered":
        raise ValueError(f"naming: expected 'numbered' or 'path', found {naming!r}")
    seen: dict[str, int] = {}
    folders = []
    for p in paths:
        stem = Path(p).stem or "session"
        seen[stem] = seen.get(stem, 0) + 1
        folders.append(Path(out) / (stem if seen[stem] == 1 else f"{stem}_{seen[stem]}"))
    return folders


def path_names(paths: Sequence[PathLike]) -> list[str]:
    """Folder names from the session paths alone: the stem where it is unique, else the shortest path suffix that
    tells the sessions apart, its parts joined by '-' (a/trial.mat, b/trial.mat → a-trial, b-trial; other.npz →
    other). Deterministic: a session's name depends on the set of paths, never on their order. Names are compared
    case-insensitively (a case-insensitive file system would merge S and s); paths that differ only by their
    extension get it appended (s-npz, s-mat), anything still equal a hash of the path.
    """
    parts, full = [], []
    for p in paths:
        q = Path(os.path.normpath(Path(p).expanduser().absolute()))
        parts.append([*q.parent.parts[1:], q.stem or "session"])   # the anchor ('/', 'C:\\') is no name
        full.append("/".join(parts[-1]).casefold())                # the whole path without its extension
    k = [1] * len(parts)                       # suffix length of each session

    def names() -> list[str]:
        return ["-".join(parts[i][-k[i]:]) for i in range(len(parts))]

    def clashes(current: list[str], same_path: bool) -> set[int]:
        """Sessions whose name another one has: one with another path (a longer suffix helps), or with the same
        path but for the extension (same_path: no suffix helps)."""
        by_name: dict[str, list[int]] = {}
        for i, n in enumerate(current):
            by_name.setdefault(n.casefold(), []).append(i)
        return {i for group in by_name.values() for i in group
                if any((full[j] == full[i]) == same_path for j in group if j != i)}

    while True:                                # every clashing session one part longer, all at once
        grow = [i for i in clashes(names(), False) if k[i] < len(parts[i])]
        if not grow:
            break
        for i in grow:
            k[i] += 1
    current = names()
    for i in clashes(current, True):           # a/s.npz, a/s.mat: the extension appended (s-npz, s-mat)
        current[i] += "-" + (Path(paths[i]).suffix.lstrip(".") or "dir")
    for i in clashes(current, True) | clashes(current, False):     # still equal (case only, …): a hash of the path
        current[i] += "-" + hashlib.sha1(str(paths[i]).encode()).hexdigest()[:8]
    return current


def distinct_sessions(paths: Sequence[PathLike]) -> tuple[list[str], dict[str, int]]:
    """Absolute session paths with repeats removed (the same file given twice is computed once), and how many
    times each repeated one was given ({path: count}, empty when none). Identity is the real path (symlinks and
    '..' resolved); the first spelling given is kept."""
    files, seen, counts = [], {}, {}
    for p in paths:
        path = str(Path(p).expanduser().absolute())
        key = os.path.realpath(path)
        if key in seen:
            counts[seen[key]] = counts.get(seen[key], 1) + 1
            continue
        seen[key] = path
        files.append(path)
    return files, counts


def local_workers(workers: Optional[int], n_sessions: int) -> int:
    """Processes of the local cluster: --workers (default the CPU count), at most one per session."""
    return min(workers or os.cpu_count() or 1, max(n_sessions, 1))


def run_one(path: str, out_dir: str, options: CalibrateOptions) -> dict:
    """The worker task: read one session, calibrate and smooth it, write its folder. Never raises.

    Args:
        path: session file (absolute, as the worker sees it).
        out_dir: this session's output folder.
        options: `CalibrateOptions` (keyframe rate, weak-data policy).

    Returns:
        {"session", "path", "out", "status": "ok"|"failed", "time_s", "error_deg" (RMS vs quat truth over
        movement, None without truth), "error" ("" when ok)} plus, when ok, the scores of
        `calibrate_path` (norm_before, norm_after, converged, iterations, identifiable, ...).
    """
    from imugraph.commands.calibrate import calibrate_path

    start = time.perf_counter()
    row = {"session": Path(path).stem, "path": path, "out": out_dir}
    try:
        result = calibrate_path(path, out_dir, options)       # quiet progress: prints nothing
    except Exception as exc:      # noqa: BLE001 — any failure is this session's, reported, not raised
        return {**row, "status": "failed", "time_s": time.perf_counter() - start, "error_deg": None,
                "error": one_line(exc)}
    result.pop("table", None)
    result.pop("session", None)
    return {**row, **result, "status": "ok", "time_s": time.perf_counter() - start,
            "error_deg": result.get("orientation_rms_deg"), "error": ""}


@contextlib.contextmanager
def dask_client(scheduler: Optional[str] = None, workers: Optional[int] = None,
                timeout_s: float = 10.0) -> Iterator["object"]:
    """A `distributed.Client`: to `scheduler`, else to a new local cluster of `workers` processes.

    Args:
        scheduler: address of a running scheduler (e.g. tcp://10.0.0.5:8786), or None.
        workers: local worker processes (default: the CPU count); ignored with a scheduler.
        timeout_s: how long to wait for the scheduler to answer.

    Raises:
        SessionError: the scheduler does not answer (field 'scheduler').
    """
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout=timeout_s)
        except (OSError, ValueError, TypeError) as exc:
            raise SessionError(scheduler, "scheduler", f"no scheduler answering ({one_line(exc)})",
                               "the address of a running dask scheduler, e.g. tcp://host:8786") from None
        with client:
            yield client
        return
    n = workers or os.cpu_count() or 1
    try:
        with _sigint_ignored():      # the worker processes inherit it: Ctrl-C is the client's to handle (below)
            cluster = LocalCluster(n_workers=n, processes=True, threads_per_worker=1, dashboard_address=None,
                                   silence_logs=logging.ERROR)
    except KeyboardInterrupt:
        raise
    except Exception as exc:      # noqa: BLE001 — e.g. RuntimeError "Nanny failed to start" (no memory, no ports)
        raise SessionError("local cluster", "workers", f"{n} worker processes that failed to start "
                           f"({one_line(exc)})", "a cluster that starts (fewer --workers, or --scheduler "
                           "ADDRESS of a running one)") from None
    with cluster, Client(cluster) as client:
        yield client


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the local cluster's processes are spawned (they inherit the disposition: a terminal's
    Ctrl-C, sent to the whole process group, then stops only the client, which cancels the tasks and closes the
    cluster — instead of ~65 lines of tracebacks from the dying workers). Restored afterwards; a no-op off the
    main thread (signal handlers can only be set there)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C during `run_batch`: the tasks were cancelled and the cluster closed; `rows` holds the sessions that
    had finished (in the order of `paths`), so that the caller can still write their summary."""

    def __init__(self, rows: list, total: int):
        super().__init__(f"{len(rows)} of {total} sessions finished")
        self.rows, self.total = rows, total


def run_batch(paths: Sequence[PathLike], out: PathLike, *, scheduler: Optional[str] = None,
              workers: Optional[int] = None, options: CalibrateOptions = CalibrateOptions(),
              progress: bool = True, naming: str = "path") -> list[dict]:
    """Calibrate and smooth every session on Dask; one folder per session under `out`.

    Args:
        paths: session files or x-IMU3 folders; a file given more than once is computed once (`distinct_sessions`).
        out: output root (created; removed again if this call created it and fails before writing anything, e.g.
            a scheduler that does not answer); the distinct session i goes to `output_folders(files, out, naming)[i]`.
        scheduler: address of an existing cluster; None for a local cluster of processes.
        workers: processes of the local cluster (default: the CPU count, at most one per session).
        options: `CalibrateOptions` of every session.
        progress: a tqdm bar on stderr, and one line per failed session.
        naming: "path" (default since U23: the shortest distinguishing path suffix, independent of the order) or
            "numbered" (stem, stem_2, … in the order given: the behaviour before).

    Returns:
        One row per distinct session, in the order of their first appearance in `paths` (see `run_one`).

    Raises:
        SessionError: `out` cannot be created, the scheduler does not answer, or the local cluster does not start.
        BatchInterrupted: Ctrl-C (a KeyboardInterrupt): the unfinished tasks cancelled, the cluster closed, the
            finished sessions' rows attached.
    """
    from distributed import as_completed
    from tqdm import tqdm

    from imugraph.commands.common import _make_out_dir, _remove_empty

    # created and checked writable (a real write) before any session runs: SessionError field 'out'
    root, created = _make_out_dir(str(Path(out).expanduser().absolute()), "batch")
    # absolute paths: a worker of an existing cluster does not share the client's working folder
    files, _ = distinct_sessions(paths)
    folders = [str(f) for f in output_folders(files, root, naming)]
    rows: list[Optional[dict]] = [None] * len(files)
    try:
        with dask_client(scheduler, local_workers(workers, len(files))) as client:
            _collect(client, files, folders, options, rows, progress, as_completed, tqdm)
    except KeyboardInterrupt:
        raise BatchInterrupted([r for r in rows if r is not None], len(files)) from None
    except Exception:       # a scheduler that does not answer, a cluster that does not start: no empty --out left
        _remove_empty(created)
        raise
    return [r for r in rows if r is not None]


def _collect(client, files: list, folders: list, options: CalibrateOptions, rows: list, progress: bool,
             as_completed, tqdm) -> None:
    """Submit one `run_one` per session and fill `rows` as they complete; on Ctrl-C cancel what is left."""
    # pure=False: every task runs (a repeated path was already removed by distinct_sessions)
    futures = [client.submit(run_one, f, d, options, pure=False, key=f"imugraph-{i}-{Path(f).stem}")
               for i, (f, d) in enumerate(zip(files, folders))]
    try:
        _gather(futures, files, folders, rows, progress, as_completed, tqdm)
    except KeyboardInterrupt:
        with contextlib.suppress(Exception):
            client.cancel([f for f in futures if not f.done()])
        for i, fut in enumerate(futures):            # finished while the interrupt was handled
            if rows[i] is None and fut.status == "finished":
                with contextlib.suppress(Exception):
                    rows[i] = fut.result(timeout=1)
        raise


def _gather(futures: list, files: list, folders: list, rows: list, progress: bool, as_completed, tqdm) -> None:
    """The progress bar and rows of `run_batch` as the futures complete."""
    index = {fut.key: i for i, fut in enumerate(futures)}
    bar = tqdm(total=len(futures), unit="session", file=sys.stderr, disable=not progress, dynamic_ncols=True)
    with bar:
        for fut in as_completed(futures):
            i = index[fut.key]
            try:
                row = fut.result()
            except Exception as exc:  # noqa: BLE001 — a worker that died (KilledWorker) or a lost task
                row = {"session": Path(files[i]).stem, "path": files[i], "out": folders[i],
                       "status": "failed", "time_s": None, "error_deg": None, "error": one_line(exc)}
            rows[i] = row
            if row["status"] != "ok" and progress:
                bar.write(f"{Path(folders[i]).name}: failed: {row['error']}", file=sys.stderr)   # the unique name
            bar.update(1)


def _cell(value) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, float):
        return f"{value:.3f}"
    return str(value)


def summary_table(rows: Sequence[dict]) -> str:
    """Plain aligned table: session, its folder under --out (blank for a failed session: nothing written), status,
    time (s), error vs truth (°, blank without truth), error."""
    head = ("session", "folder", "status", "time_s", "error_deg", "error")

    def cells_of(r: dict) -> list[str]:
        folder = Path(r["out"]).name if r.get("out") and r.get("status") == "ok" else ""
        return [_cell(r.get("session")), folder, *(_cell(r.get(c)) for c in head[2:])]

    cells = [cells_of(r) for r in rows]
    widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, h in enumerate(head)]

    def line(values) -> str:
        return "  ".join(v.ljust(w) if i in (0, 1, 2, 5) else v.rjust(w)
                         for i, (v, w) in enumerate(zip(values, widths))).rstrip()

    ok = sum(r.get("status") == "ok" for r in rows)
    return "\n".join([line(head), line("-" * w for w in widths), *map(line, cells),
                      f"{ok}/{len(rows)} sessions ok"])


def write_summary(out: PathLike, rows: Sequence[dict], meta: Optional[dict] = None) -> tuple[Path, Path]:
    """Write out/summary.json ({"sessions": rows, "ok", "failed", **meta}) and out/summary.csv atomically.

    summary.csv holds `COLUMNS`, one line per session; empty cells where a value does not apply.
    """
    from imugraph.io.writers import atomic_write_text, json_ready

    ok = sum(r.get("status") == "ok" for r in rows)
    doc = {**(meta or {}), "ok": ok, "failed": len(rows) - ok, "sessions": list(rows)}
    root = Path(out)
    js = atomic_write_text(root / "summary.json", json.dumps(json_ready(doc), indent=1, allow_nan=False) + "\n")
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for r in rows:
        writer.writerow([_cell(r.get(c)) for c in COLUMNS])
    return js, atomic_write_text(root / "summary.csv", buffer.getvalue())
