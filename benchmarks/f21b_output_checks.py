"""Session 21, helper F21b: what calibrate's figures show against what its console prints, on BROAD trials
(defects 5 and 6 of the acceptance run), and that the outputs themselves did not change.

Per trial: `imugraph calibrate` (commands.calibrate.calibrate_path) into OUT/<trial>, then
  - console: the printed orientation RMS (commands.common.orientation_score: best time shift and heading offset);
  - heading.png before the fix: RMS of the heading error yaw(nRb_est · nRb_refᵀ) over every sample with a
    reference, unaligned (what io/figures._plot_heading_error printed); after: the same at the console's
    alignment over `movement` (io/figures._aligned_estimate), and the total angle there (should equal the console);
  - calibration.png's calibrated norm inside the calibration's disturbance windows: min–max of |D⁻¹(y − o)| with
    y the raw field (before the fix) and y = Calibration.corrected(t, y) (after; NaN rows = unexplained, skipped);
  - with --ref DIR: whether calibration.json and orientation.npz are byte-identical to DIR/<trial>/ (a run of the
    code before the fix, e.g. from a clean clone).

    .venv/bin/python benchmarks/f21b_output_checks.py 01 32 --out /tmp/f21b_checks [--ref DIR]
"""

from __future__ import annotations

import argparse
import filecmp
import sys
import time
from pathlib import Path

import numpy as np

from imugraph.commands.calibrate import CalibrateOptions, calibrate_path
from imugraph.config import broad_dir
from imugraph.geometry import quat_to_rotmat
from imugraph.io.figures import _aligned_estimate
from imugraph.io.readers import load_session


def _yaw_rms(q_est: np.ndarray, q_ref: np.ndarray, rows: np.ndarray) -> tuple[float, float]:
    """(heading RMS, total-angle RMS) in degrees of E = nRb_est · nRb_refᵀ over `rows`."""
    E = quat_to_rotmat(q_est[rows]) @ np.swapaxes(quat_to_rotmat(q_ref[rows]), -1, -2)
    yaw = np.rad2deg(np.arctan2(E[:, 1, 0], E[:, 0, 0]))
    total = np.rad2deg(np.arccos(np.clip((np.trace(E, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.sqrt(np.mean(yaw**2))), float(np.sqrt(np.mean(total**2)))


def check(trial: str, out_root: Path, ref_root: Path | None) -> dict:
    path = sorted(broad_dir().glob(f"{trial}_*.mat"))[0]
    out = out_root / path.stem
    cpu = time.process_time()
    result = calibrate_path(path, out, CalibrateOptions())
    cpu = time.process_time() - cpu
    session = load_session(path)
    quat = np.load(out / "orientation.npz")["quat"]
    from imugraph.io.writers import read_calibration_json
    cal = read_calibration_json(out / "calibration.json")
    known = np.all(np.isfinite(session.quat), axis=1)
    before, _ = _yaw_rms(quat, session.quat, known)
    aligned, _ = _aligned_estimate(quat, session.quat, session.movement)
    rows = known & np.all(np.isfinite(aligned), axis=1) & (session.movement if session.movement is not None else True)
    after, total = _yaw_rms(aligned, session.quat, rows)
    row = {"trial": path.stem, "console_deg": result["orientation_rms_deg"], "heading_before_deg": before,
           "heading_after_deg": after, "total_after_deg": total, "cpu_s": cpu, "windows": len(cal.disturbances)}
    if cal.disturbances:
        inside = np.zeros(session.n, bool)
        for d in cal.disturbances:
            inside |= (session.t >= d["t_start"]) & (session.t <= d["t_end"])
        raw = np.linalg.norm(cal.apply(session.mag[inside]), axis=1)
        cor = np.linalg.norm(cal.calibrated_field(session.t, session.mag)[inside], axis=1)
        cor = cor[np.isfinite(cor)]
        row.update(norm_before=(float(raw.min()), float(raw.max())),
                   norm_after=(float(cor.min()), float(cor.max())) if cor.size else None)
    if ref_root is not None:
        ref = ref_root / path.stem
        row["identical"] = all(filecmp.cmp(ref / f, out / f, shallow=False)
                               for f in ("calibration.json", "orientation.npz"))
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("trials", nargs="+", help="BROAD trial numbers, e.g. 01 32")
    p.add_argument("--out", required=True, help="output root (one calibrate folder per trial)")
    p.add_argument("--ref", default=None, help="root of a reference run (same layout) to compare bytes with")
    args = p.parse_args(argv)
    for trial in args.trials:
        r = check(trial, Path(args.out), Path(args.ref) if args.ref else None)
        line = (f"{r['trial']}: console {r['console_deg']:.2f}°  heading.png RMS before {r['heading_before_deg']:.2f}° "
                f"after {r['heading_after_deg']:.2f}° (total {r['total_after_deg']:.2f}°)  CPU {r['cpu_s']:.1f} s")
        if "norm_before" in r:
            nb, na = r["norm_before"], r["norm_after"]
            line += (f"  |m| in {r['windows']} window(s): before {nb[0]:.2f}–{nb[1]:.2f}"
                     + (f", after {na[0]:.2f}–{na[1]:.2f}" if na else ", after: all unexplained (not drawn)"))
        if "identical" in r:
            line += f"  outputs identical to --ref: {r['identical']}"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
