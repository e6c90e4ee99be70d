"""Session 22, helper F22c: the acceptance run's body-session cases (U22 defects 5, 7, 8, 15), before vs after.

Builds, in a temporary folder (nothing is written into the repository or ../shared), the cases of U22's
lib_body.py / lib_body_rt.py from the project's own body simulator:

    sess       CMU 131_01, 12 s at 60 Hz, the 7 lower-body segments (U22's lib_body.py settings)
    nomag      sess with 'mag' removed from every sensor NPZ          nanmag   sess with every mag all NaN
    dup        two segments naming the same NPZ                       badseg   a segment renamed 'LeftKnee'
    dupkey     session.json naming 'Pelvis' twice                     fewer    a sensed segment without a file
    rt_131_01 / rt_131_02   benchmarks.body_bench.simulated_session(name, seed 0, 20 s), 17 IMUs

and reads each back with `read_body_session`: "read" with a digest of every array (equal digests = bit-identical
sessions between two code versions) or the error line. With --mocap also `imugraph mocap` (batch) on sess, nomag,
nomag --mag and dup: exit code, max joint error against the simulation's truth, digest of mocap.npz.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/f22c_body_checks.py [--mocap]
    PYTHONPATH=/tmp/f22c_ref OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/f22c_body_checks.py [--mocap]
                          (the same with a clean clone's imugraph and benchmarks: before; the line "imugraph
                          from" says which was used)
Uses only APIs both versions have (write_body_session, read_body_session, imugraph.cli.main).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import resource
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))     # appended: PYTHONPATH=<clean clone> wins (before)


def digest(session) -> str:
    """sha1 over t and every sensor's gyr, acc, mag, quat (NaN-safe: raw bytes), first 12 hex digits."""
    h = hashlib.sha1(np.ascontiguousarray(session.t).tobytes())
    for seg in sorted(session.sensors):
        s = session.sensors[seg]
        for x in (s.gyr, s.acc, s.mag, s.quat):
            if x is not None:
                h.update(seg.encode() + np.ascontiguousarray(x).tobytes())
    return h.hexdigest()[:12]


def lower_body_sim(folder: Path) -> Path:
    """U22's lib_body.py session: CMU 131_01, 12 s at 60 Hz, lower body, seed 0."""
    from imugraph.body.skeleton import LOWER_BODY
    from imugraph.config import data_dir
    from imugraph.io.body_session import write_body_session
    from imugraph.sim.body import BodyMotion, motion_from_bvh, random_placements, simulate_body
    from imugraph.sim.sensors import SensorParams

    skel, motion = motion_from_bvh(str(data_dir() / "cmu_bvh" / "scaled_131_01.bvh"), rate_hz=60.0, duration_s=12.0)
    idx = [skel.index(n) for n in LOWER_BODY]
    skel = skel.subset(LOWER_BODY)
    motion = BodyMotion(motion.t, skel.names, motion.n_quat[:, idx], motion.n_pos[:, idx])
    rng = np.random.default_rng(0)
    p = SensorParams(gyro_noise=np.full(3, 0.01), acc_noise=np.full(3, 0.05), mag_noise=np.full(3, 0.01))
    return write_body_session(folder, simulate_body(motion, skel, random_placements(skel, rng), p, rng,
                                                    name="cmu131_01"))


def _variant(src: Path, dst: Path, npz=None, doc=None, text=None) -> Path:
    shutil.copytree(src, dst)
    for f in sorted(dst.glob("*.npz")) if npz else []:
        if f.name != "truth.npz":
            z = dict(np.load(f))
            npz(z)
            np.savez(f, **z)
    if doc:
        d = json.loads((dst / "session.json").read_text())
        doc(d)
        (dst / "session.json").write_text(json.dumps(d))
    if text:
        (dst / "session.json").write_text(text((dst / "session.json").read_text()))
    return dst


def build(tmp: Path) -> dict:
    from benchmarks.body_bench import simulated_session
    from imugraph.io.body_session import write_body_session

    sess = lower_body_sim(tmp / "sess")
    cases = {"sess": sess}
    cases["nomag"] = _variant(sess, tmp / "nomag", npz=lambda z: z.pop("mag"))
    cases["nanmag"] = _variant(sess, tmp / "nanmag", npz=lambda z: z.update(mag=np.full_like(z["mag"], np.nan)))
    cases["dup"] = _variant(sess, tmp / "dup", doc=lambda d: d["sensors"].update(RightUpperLeg="Pelvis.npz"))
    cases["badseg"] = _variant(sess, tmp / "badseg",
                               doc=lambda d: d["sensors"].update(LeftKnee=d["sensors"].pop("LeftLowerLeg")))
    cases["dupkey"] = _variant(sess, tmp / "dupkey",
                               text=lambda s: s.replace('"sensors": {', '"sensors": {"Pelvis": "Pelvis.npz", ', 1))
    cases["fewer"] = _variant(sess, tmp / "fewer", doc=lambda d: d["sensors"].pop("RightFoot"))
    for name in ("cmu131_01", "cmu131_02"):
        _, ses, _ = simulated_session(name, seed=0, duration_s=20.0)
        cases[f"rt_{name[3:]}"] = write_body_session(tmp / f"rt_{name}", ses)
    return cases


def mocap(folder: Path, out: Path, *extra: str) -> str:
    """`imugraph mocap FOLDER --out OUT --quiet [extra]`: exit code, max joint error, mocap.npz digest."""
    from imugraph.cli import main as cli

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = cli(["mocap", str(folder), "--out", str(out), "--quiet", *extra])
    if code != 0:
        return f"exit {code}: {err.getvalue().strip()[-160:]}"
    info = json.loads((out / "mocap_info.json").read_text())
    worst = (info.get("scores") or {}).get("joint_rmse_max_deg", float("nan"))     # the CLI's own score
    h = hashlib.sha1((out / "mocap.npz").read_bytes()).hexdigest()[:12]
    return f"exit 0, max joint RMS {float(worst):.2f}°, mocap.npz {h}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="f22c_body_checks.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mocap", action="store_true", help="also run `imugraph mocap` on sess, nomag (±--mag), dup")
    args = ap.parse_args(argv)
    import imugraph
    from imugraph.io.body_session import read_body_session

    print(f"imugraph from {Path(imugraph.__file__).parent}", flush=True)
    with tempfile.TemporaryDirectory(prefix="f22c_body_") as d:
        tmp = Path(d)
        cases = build(tmp)
        for name, folder in cases.items():
            try:
                s = read_body_session(folder)
                print(f"{name:10s} read: {len(s.sensors)} sensors, {s.n} samples, digest {digest(s)}"
                      + (f", no_mag {len(s.meta['no_mag'])}" if s.meta.get("no_mag") else ""), flush=True)
            except Exception as exc:                                     # noqa: BLE001 (reported, not raised)
                print(f"{name:10s} {type(exc).__name__}: {str(exc).replace(str(tmp), '<tmp>')[:230]}", flush=True)
        if args.mocap:
            for name, extra in (("sess", ()), ("nomag", ()), ("nomag", ("--mag",)), ("dup", ())):
                res = mocap(cases[name], tmp / f"out_{name}{'_mag' if extra else ''}", *extra)
                print(f"mocap {name} {' '.join(extra):5s} {res.replace(str(tmp), '<tmp>')}", flush=True)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    print(f"CPU {ru.ru_utime + ru.ru_stime:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
