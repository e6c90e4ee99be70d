"""Session 22, helper F22b (U22 defect 1): how often calibrate() returns a dip outside [−90°, 90°], and whether
smoothing with its calibration reproduces calibrate's own orientation (the calibrate → smooth --calibration round trip).

Per BROAD trial, on the first 60 s ("crop") or the whole trial ("whole"):
  - calibrate(session, Options(), allow_weak=True): its dip and its orientation's RMS error vs the optical truth;
  - smooth_fixed(session, calibration, field_sigma=(0.015, 0.003, 0.015)) — what `smooth --calibration` runs —
    and its RMS error; also with the calibration's dip set to 180° − dip by hand ("mirrored": the other branch,
    which a calibration.json written before the fold held);
  - with --md5: md5 of the calibration's (D, o, dip, bias) and the orientation (bit-identity checks between a
    clean clone and the working tree: run once with PYTHONPATH=/tmp/clone).

    .venv/bin/python benchmarks/f22b_dip_crops.py crop [--trials 06 21] [--md5]
    .venv/bin/python benchmarks/f22b_dip_crops.py whole --trials 01 06 32 --md5

"roundtrip" (U22's dip_roundtrip.sh through the CLI): the first 60 s of a trial (default 06) written as an NPZ into a
temporary folder, then `calibrate`, `smooth --calibration` (with and without --no-field), `stream --lag 2
--calibration`, the same two with the calibration's dip set to 180° − dip by hand, and `stream --lag 2
--bootstrap-s 60` / `59` (a bootstrap window covering the whole session: calibrate's result is the stream's start);
prints each command's orientation RMS lines.

    .venv/bin/python benchmarks/f22b_dip_crops.py roundtrip [--trials 06]
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from dataclasses import replace

import numpy as np

FIELD_SIGMA = (0.015, 0.003, 0.015)


def md5(*arrays) -> str:
    h = hashlib.md5()
    for a in arrays:
        h.update(np.ascontiguousarray(np.asarray(a, float)).tobytes())
    return h.hexdigest()[:10]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__)
    ap.add_argument("span", choices=("crop", "whole", "roundtrip"),
                    help="first 60 s of each trial, the whole trial, or the CLI round trip on a 60 s crop")
    ap.add_argument("--trials", nargs="*", default=None, help="trial number prefixes (default: all .mat trials)")
    ap.add_argument("--crop-s", type=float, default=60.0, help="crop length, s (default 60)")
    ap.add_argument("--md5", action="store_true", help="print md5 of the calibration and orientation")
    args = ap.parse_args(argv)

    from imugraph.calibration.initial import initial_calibration
    from imugraph.calibration.ml import Options, calibrate
    from imugraph.config import broad_dir
    from imugraph.errors import CalibrationError
    from imugraph.evaluate import orientation_error
    from imugraph.graphs.cpp_smoother import smooth_fixed
    from imugraph.io.readers import load_session

    files = sorted(broad_dir().glob("*.mat"))
    if args.trials:
        files = [f for f in files if any(f.name.startswith(p) for p in args.trials)]
    if args.span == "roundtrip":
        for f in files if args.trials else [f for f in files if f.name.startswith("06")]:
            roundtrip(f, args.crop_s)
        return 0
    print(f"{'trial':32s} span  dip₀°   dip°     folded  calibrate°  smooth_fixed°  mirrored-dip smooth°  cpu_s")
    rows = []
    for f in files:
        s = load_session(f)
        if args.span == "crop":
            s = s.slice(0, int(args.crop_s * s.rate))          # as U22's mk.py / dip_crops.py
        try:       # step 1's dip (calibration/initial.py), the ML loop's start: near 90° the loop can cross it
            dip0 = f"{np.rad2deg(initial_calibration(s).dip_rad):6.2f}"
        except CalibrationError:
            dip0 = "  weak"
        c0 = time.process_time()
        est = calibrate(s, Options(progress=False), allow_weak=True)
        cal = est.calibration
        q = smooth_fixed(s, cal, field_sigma=FIELD_SIGMA)
        mirrored = replace(cal, dip_deg=180.0 - cal.dip_deg)
        q_m = smooth_fixed(s, mirrored, field_sigma=FIELD_SIGMA)
        cpu = time.process_time() - c0

        def err(qq):
            return orientation_error(qq, s.quat, s.movement, s.rate).rms_deg
        e_cal, e_s, e_m = err(est.quat), err(q), err(q_m)
        folded = bool((est.info or {}).get("dip_folded", False))
        rows.append((cal.dip_deg, e_cal, e_s))
        line = (f"{f.name[:32]:32s} {args.span:5s} {dip0} {cal.dip_deg:7.2f}  {str(folded):6s}  {e_cal:9.2f}  "
                f"{e_s:12.2f}  {e_m:18.2f}  {cpu:6.1f}")
        if args.md5:
            line += f"  cal {md5(cal.D, cal.o, [cal.dip_deg], cal.gyro_bias)} quat {md5(est.quat)} smooth {md5(q)}"
        print(line, flush=True)
    if rows:
        a = np.array(rows)
        out = np.sum((a[:, 0] > 90) | (a[:, 0] < -90))
        print(f"mean: calibrate {a[:, 1].mean():.2f}°, smooth_fixed {a[:, 2].mean():.2f}°; dip outside ±90°: {out} of "
              f"{len(a)}; max |calibrate − smooth_fixed| {np.max(np.abs(a[:, 1] - a[:, 2])):.2f}°")
    return 0


def roundtrip(path, crop_s: float) -> None:
    """The CLI round trip on the first crop_s seconds of one trial (module docstring)."""
    import contextlib
    import io
    import json
    import tempfile
    from pathlib import Path

    from imugraph.cli import main as cli
    from imugraph.io.readers import load_session

    s = load_session(path)
    n = int(crop_s * s.rate)                                # as U22's mk.py (odd/good.npz)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        npz = tmp / "crop.npz"
        np.savez(npz, t=s.t[:n], gyr=s.gyr[:n], acc=s.acc[:n], mag=s.mag[:n], quat=s.quat[:n], movement=s.movement[:n])

        def run(label, *argv):
            out, err = io.StringIO(), io.StringIO()
            c0 = time.process_time()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = cli([*argv, "--quiet"])
            lines = [ln.strip() for ln in out.getvalue().splitlines() if "dip " in ln or "RMS" in ln]
            print(f"{label:38s} rc {code}  {' | '.join(lines)}  ({time.process_time() - c0:.1f} s CPU)", flush=True)

        cal = tmp / "cal" / "calibration.json"
        run("calibrate", "calibrate", str(npz), "--out", str(tmp / "cal"))
        mirrored = tmp / "mirrored.json"
        c = json.loads(cal.read_text())
        c["dip_deg"] = 180.0 - c["dip_deg"]
        mirrored.write_text(json.dumps(c))
        for name, file in (("", cal), (" (dip 180° − dip)", mirrored)):
            run("smooth --calibration" + name, "smooth", str(npz), "--calibration", str(file), "--out", str(tmp / "s"))
            run("smooth --calibration --no-field" + name, "smooth", str(npz), "--calibration", str(file), "--no-field",
                "--out", str(tmp / "s"))
            run("stream --lag 2 --calibration" + name, "stream", str(npz), "--lag", "2", "--calibration", str(file),
                "--out", str(tmp / "st"))
        for b in ("60", "59"):
            run(f"stream --lag 2 --bootstrap-s {b}", "stream", str(npz), "--lag", "2", "--bootstrap-s", b,
                "--out", str(tmp / "st"))


if __name__ == "__main__":
    sys.exit(main())
