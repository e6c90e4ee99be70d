"""Plot how the streamed calibration converged: the figure issue 3 asks the stream's history for.

    .venv/bin/imugraph stream SESSION --out OUT            # writes OUT/calibration_history.json
    .venv/bin/python examples/plot_convergence.py OUT [--batch CALIBRATION_JSON] [--png OUT/convergence.png]

Reads `calibration_history.json` (docs/stream.md: `start`, then one row per `calib_every_s` with t, D, o,
dip_deg and their std) and draws, against stream time, the hard-iron offset o (3 axes), the diagonal of the
soft-iron matrix D and the dip as differences to a reference, each with its ±1 std band where the row has
one: the reference is a batch calibration.json given with --batch (`imugraph calibrate` on the whole
session: what the stream should converge to; the start then a dotted line), else the start calibration. The PNG is written atomically (imugraph.io.figures.save_figure_atomic).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from imugraph.errors import SessionError


def read_history(path: Path) -> tuple[dict, list[dict]]:
    """(start calibration dict, history rows) of a calibration_history.json; SessionError when malformed."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        found = (exc.strerror or type(exc).__name__) if isinstance(exc, OSError) else f"not JSON ({exc})"
        raise SessionError(str(path), "<file>", found, "a readable calibration_history.json (`imugraph stream "
                           "--out OUT` writes OUT/calibration_history.json)") from None
    rows = doc.get("calibration_history") if isinstance(doc, dict) else None
    if not isinstance(rows, list) or not rows:
        raise SessionError(str(path), "calibration_history", "missing or empty", "a non-empty list of rows")
    return doc.get("start") or {}, rows


def series(rows: list[dict]) -> dict[str, np.ndarray]:
    """Arrays over the rows: t (K,), o (K, 3), d = diag D (K, 3), dip (K,), and their std (NaN where absent)."""
    def std(r, key, shape):
        s = (r.get("std") or {}).get(key)
        return np.full(shape, np.nan) if s is None else np.asarray(s, float)
    out = {"t": np.array([r["t"] for r in rows], float),
           "o": np.array([r["o"] for r in rows], float),
           "d": np.array([np.diag(np.asarray(r["D"], float)) for r in rows]),
           "dip": np.array([r.get("dip_deg", np.nan) for r in rows], float)}
    out["o_std"] = np.array([std(r, "o", (3,)) for r in rows])
    out["d_std"] = np.array([np.diag(std(r, "D", (3, 3))) for r in rows])
    out["dip_std"] = np.array([float(std(r, "dip_deg", ())) for r in rows])
    return out


def plot(history: Path, png: Path, batch: Path | None = None) -> Path:
    """Draw the convergence figure of `history` into `png`; returns the path written."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from imugraph.io.figures import save_figure_atomic

    start, rows = read_history(history)
    s = series(rows)
    ref = json.loads(batch.read_text()) if batch else None
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    panels = [("o", "hard-iron offset o", lambda c: np.asarray(c["o"], float)),
              ("d", "soft iron: diagonal of D", lambda c: np.diag(np.asarray(c["D"], float))),
              ("dip", "dip (°)", lambda c: np.atleast_1d(float(c.get("dip_deg", np.nan))))]
    base, base_name = (ref, "batch") if ref else (start, "start")
    for ax, (key, title, pick) in zip(axes, panels):
        y = s[key].reshape(len(s["t"]), -1)
        e = s[f"{key}_std"].reshape(len(s["t"]), -1)
        y0 = pick(base) if base else np.zeros(y.shape[1])       # drawn as the difference to the reference
        for j in range(y.shape[1]):
            d = y[:, j] - y0[j]
            line, = ax.plot(s["t"], d, label=f"{'xyz'[j]}" if y.shape[1] > 1 else "streamed")
            ax.fill_between(s["t"], d - e[:, j], d + e[:, j], color=line.get_color(), alpha=0.2)
            if ref and start:
                ax.axhline(pick(start)[j] - y0[j], color=line.get_color(), ls=":", lw=1)
        ax.axhline(0.0, color="k", ls="--", lw=0.8)
        ax.set_title(f"{title}: streamed − {base_name}" if base else title)
        ax.legend(loc="best", fontsize=8)
    axes[-1].set_xlabel(f"stream time (s)   — streamed ±1 std, - - {base_name}" + (", ··· start" if ref and start else ""))
    fig.tight_layout()
    out = save_figure_atomic(fig, png)
    plt.close(fig)
    return out


def history_path(out: Path) -> Path:
    """The calibration_history.json meant by OUT: OUT itself when it names a .json file, else OUT/
    calibration_history.json — also when the folder does not exist, so that the error names the file looked for
    (U23 defect 14: it named the folder)."""
    return out if out.suffix.lower() == ".json" and not out.is_dir() else out / "calibration_history.json"


def main(argv: list[str] | None = None) -> int:
    """Command line: OUT folder (or a calibration_history.json), --batch, --png."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="the folder `imugraph stream --out` wrote, or its calibration_history.json")
    ap.add_argument("--batch", default=None, help="a batch calibration.json to draw as the target")
    ap.add_argument("--png", default=None, help="output PNG (default: convergence.png beside the history)")
    a = ap.parse_args(argv)
    hist = history_path(Path(a.out))
    png = Path(a.png) if a.png else hist.parent / "convergence.png"
    try:
        print(f"wrote {plot(hist, png, Path(a.batch) if a.batch else None)}")
    except SessionError as exc:
        print(f"plot_convergence: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
