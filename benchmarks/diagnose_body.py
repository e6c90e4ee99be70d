"""Issue 5 (body sessions): validation harness of `imugraph diagnose` on multi-IMU sessions (imugraph.diagnose.body).

Hosts (nothing copied from the data directory):
    cmu_lower     CMU 131_02 BVH, the 7 lower-body sensors, simulated (benchmarks.body_bench: random placements
                  ≤ 30°, MEMS noise and biases), --duration s after the 3 s N-pose, 60 Hz
    xsens_lower   the Xsens MVN BVH of the gaittoolbox walk, same
    xsens_full    the same motion, all 17 sensors
    real_walk     the REAL gaittoolbox walk (7 Xsens MTw, 100 Hz, 25 s)
Per host and label (none, soft_tissue, gyro_bias_drift, accelerometer_bias) one case: the effect's own `inject`
with randomised parameters (ranges in each module's RANGES), a random sensor and, for soft_tissue, a random
window in half of the cases; the label is hidden from the diagnoser (it gets the modified session only).
Prints the confusion matrix (true label → verdict), the sensor hit rate, the window IoU of windowed
soft_tissue cases (diagnosed t_start/t_end = span of the sensor's located gap), the held-out shrink of the
verdict's effect, and the time per case; then the real walk with nothing injected, with the left thigh's
entries (issue 4 found its axial rotation disagreeing with Vicon).

    .venv/bin/python benchmarks/diagnose_body.py [--hosts cmu_lower,xsens_lower,xsens_full,real_walk]
                                                 [--duration 20] [--seed 0] [--out diagnose_body.json]
    .venv/bin/python benchmarks/diagnose_body.py --absorption LeftLowerLeg --hosts xsens_lower --out absorption.json
        (how much of an injected drift / acc bias the base fit's own bias estimates take, docs §3)
    .venv/bin/python benchmarks/diagnose_body.py --hosts real_walk --labels none --profile --dump-dir DIR
        (cProfile of the cases: top functions by cumulative and own CPU time printed, the stats written to
        bench_out/<out>.prof; --dump-dir: every case's full diagnosis.json (timing removed) into bench_out/DIR)
    .venv/bin/python benchmarks/diagnose_body.py --compare DIR_A DIR_B
        (the largest absolute difference of every number between the dumped diagnoses of two runs, and the
        verdicts: a speed change that should not change results must print 0 differences)
    .venv/bin/python benchmarks/diagnose_body.py ... --opt FIELD=VALUE
        (a BodyDiagnoseOptions field, e.g. --opt refit_located_only=True; repeatable)
    .venv/bin/python benchmarks/diagnose_body.py --hosts xsens_lower,cmu_lower,xsens_full,real_walk --diagnose-hosts real_walk
        (the harness's real-walk cases only: the other hosts' cases are drawn, not diagnosed)
Writes bench_out/<out>.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.output import write_json  # noqa: E402

LABELS = ("none", "soft_tissue", "gyro_bias_drift", "accelerometer_bias")
HOSTS = ("cmu_lower", "xsens_lower", "xsens_full", "real_walk")


def host_session(name: str, duration: float, seed: int):
    """The undisturbed body session of a host (module doc)."""
    if name == "real_walk":
        from imugraph.config import data_dir
        from imugraph.io.body_session import read_body_session
        return read_body_session(data_dir() / "gaittoolbox" / "rawimu")
    from benchmarks.body_bench import simulated_session
    motion = {"cmu_lower": "cmu131_02", "xsens_lower": "xsens", "xsens_full": "xsens"}[name]
    _, session, _ = simulated_session(motion, seed, duration, lower=name.endswith("lower"))
    return session


def iou(a0, a1, b0, b1) -> float:
    if None in (a0, a1, b0, b1):
        return 0.0
    inter = max(0.0, min(a1, b1) - max(a0, b0))
    union = max(a1, b1) - min(a0, b0)
    return inter / union if union > 0 else 0.0


def run_case(host: str, session, label: str, rng: np.random.Generator, options=None, dump: Path | None = None,
             diagnose: bool = True) -> dict | None:
    from imugraph.diagnose.body.run import BodyDiagnoseOptions, body_effects, diagnose_body

    truth = {"sensor": None, "t_start": None, "t_end": None, "params": {}}
    if label != "none":
        eff = next(e for e in body_effects() if e.name == label)
        window = "random" if (label == "soft_tissue" and rng.random() < 0.5) else None
        session, truth = eff.inject(session, rng, window=window) if label == "soft_tissue" else \
            eff.inject(session, rng)
    if not diagnose:                    # --diagnose-hosts: the case is drawn (the random stream advances) only
        return None
    t0, c0 = time.perf_counter(), time.process_time()
    d = diagnose_body(session, options or BodyDiagnoseOptions())
    secs, cpu = time.perf_counter() - t0, time.process_time() - c0
    if dump is not None:
        js = d.to_json()
        js.pop("timing", None)
        write_json(str(dump / f"{host}_{label}.json"), {"truth": truth, "diagnosis": js})
    top = next((e for e in d.effects if e["name"] == d.verdict and e["sensor"] == d.sensor), None)
    rec = {"host": host, "label": label, "truth": truth, "verdict": d.verdict, "sensor": d.sensor,
           "sensor_hit": d.sensor == truth.get("sensor") if label != "none" else d.sensor is None,
           "seconds": secs, "cpu_s": cpu, "timing": d.timing, "n_sensors": len(session.sensors),
           "duration_s": float(session.t[-1] - session.t[0]),
           "shrink": None if top is None else top["shrink"], "loglik_gain": None if top is None else top["loglik_gain"],
           "effects_top5": [{k: e[k] for k in ("name", "sensor", "channel", "loglik_gain", "loglik_gain_folds", "shrink",
                                               "size", "significant", "relevant", "stage")} for e in d.effects[:5]],
           "soft_tissue_per_sensor": {e["sensor"]: {k: e[k] for k in ("loglik_gain", "shrink", "size", "significant",
                                                                       "relevant", "stage", "channel", "params")}
                                      for e in d.effects if e["name"] == "soft_tissue"},
           "gaps": d.gaps, "locations": d.locations[:10]}
    if label == "soft_tissue" and truth.get("t_start") is not None:
        mine = [e for e in d.effects if e["name"] == "soft_tissue" and e["sensor"] == truth["sensor"]]
        t_s, t_e = (mine[0]["t_start"], mine[0]["t_end"]) if mine else (None, None)
        rec["window_iou"] = iou(t_s, t_e, truth["t_start"], truth["t_end"])
    print(f"  {host:<12} {label:<19} → {d.verdict:<19} {str(d.sensor):<14} (true sensor {truth.get('sensor')}) "
          f"shrink {rec['shrink'] if rec['shrink'] is None else round(rec['shrink'], 2)}  {secs:.1f} s ({cpu:.1f} s CPU; "
          f"{ {k: round(v, 1) for k, v in d.timing.items()} })", flush=True)
    return rec


def summary(records: list) -> dict:
    conf = {a: {b: 0 for b in LABELS} for a in LABELS}
    for r in records:
        conf[r["label"]][r["verdict"] if r["verdict"] in LABELS else "none"] += 1
    injected = [r for r in records if r["label"] != "none"]
    correct = [r for r in injected if r["verdict"] == r["label"] and r["sensor_hit"]]
    ious = [r["window_iou"] for r in records if "window_iou" in r]
    shrinks = [r["shrink"] for r in correct if r["shrink"] is not None]
    sims_none = [r for r in records if r["label"] == "none" and r["host"] != "real_walk"]
    return {"confusion": conf, "top1_effect_and_sensor": len(correct) / max(len(injected), 1),
            "none_on_clean_simulations": sum(r["verdict"] == "none" for r in sims_none) / max(len(sims_none), 1),
            "window_iou": ious, "median_shrink_correct": float(np.median(shrinks)) if shrinks else None,
            "seconds": [r["seconds"] for r in records], "cpu_s": [r["cpu_s"] for r in records]}


def body_options(pairs: list):
    """BodyDiagnoseOptions with FIELD=VALUE overrides (values as python literals); unknown fields fail."""
    from benchmarks.common import option_overrides
    from imugraph.diagnose.body.run import BodyDiagnoseOptions

    return BodyDiagnoseOptions(**option_overrides(pairs, BodyDiagnoseOptions))


def absorption(host: str, sensor: str, duration: float, seed: int) -> list:
    """How much of an injected drift / accelerometer bias the BASE fit's own bias estimates take (docs §3):
    per case the fraction absorbed (1 − RMS(injected − change of the fitted bias path)/RMS(injected), a drift
    about its mean), the residual change per channel / the clean residual RMS, and the graph cost."""
    from imugraph.diagnose.body.effects.accelerometer_bias import EFFECT as ACC
    from imugraph.diagnose.body.effects.gyro_bias_drift import EFFECT as GYR
    from imugraph.diagnose.body.fit import fit_body

    def rms(x):
        return float(np.sqrt(np.mean(np.sum(np.asarray(x) ** 2, axis=-1))))

    s0 = host_session(host, duration, seed)
    f0 = fit_body(s0)
    sf0 = f0.sensors[sensor]
    out = []
    for kind, eff, strength, case_seed in (("gyr", GYR, 0.5, 1), ("gyr", GYR, 2.0, 2), ("gyr", GYR, 2.0, 5),
                                           ("acc", ACC, 0.3, 3), ("acc", ACC, 1.0, 4)):
        s1, truth = eff.inject(s0, np.random.default_rng(case_seed), sensor=sensor, strength=strength)
        f1 = fit_body(s1)
        sf1 = f1.sensors[sensor]
        inj = getattr(s1.sensors[sensor], kind) - getattr(s0.sensors[sensor], kind)
        left = inj - ((sf1.b_gyr - sf0.b_gyr) if kind == "gyr" else (sf1.b_acc - sf0.b_acc))
        ab = 1 - (rms(left - left.mean(0)) / rms(inj - inj.mean(0)) if kind == "gyr" else rms(left) / rms(inj))
        ch = {c: rms(sf1.residuals[c] - sf0.residuals[c]) / max(rms(sf0.residuals[c]), 1e-12)
              for c in sf0.residuals if sf0.residuals[c].shape[1]}
        rec = {"host": host, "sensor": sensor, "kind": kind, "strength": strength,
               "shape": truth["params"].get("shape"), "absorbed": ab, "residual_change_rel": ch,
               "cost": [f0.info["cost_final"], f1.info["cost_final"]]}
        print(f"  {kind} {strength} {rec['shape']}: absorbed {ab:.3f}; residual change / clean RMS "
              f"{ {c: round(v, 3) for c, v in ch.items()} }; cost {rec['cost'][0]:.1f} → {rec['cost'][1]:.1f}",
              flush=True)
        out.append(rec)
    return out


def _numbers(x, path=""):
    """(path, value) of every number / string / bool in a JSON tree (dict keys sorted, lists by index)."""
    if isinstance(x, dict):
        for k in sorted(x):
            yield from _numbers(x[k], f"{path}.{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from _numbers(v, f"{path}[{i}]")
    else:
        yield path, x


def compare(dir_a: str, dir_b: str) -> int:
    """Largest absolute difference of every number between the dumped diagnoses of two runs (--dump-dir)."""
    import json

    from benchmarks.output import OUT_DIR
    a_dir, b_dir = OUT_DIR / dir_a, OUT_DIR / dir_b
    n_diff = 0
    for fa in sorted(a_dir.glob("*.json")):
        fb = b_dir / fa.name
        if not fb.exists():
            print(f"{fa.name}: missing in {dir_b}")
            n_diff += 1
            continue
        ja, jb = json.loads(fa.read_text()), json.loads(fb.read_text())
        for j in (ja, jb):                  # effects keyed by (effect, sensor), not by rank
            j["diagnosis"]["effects"] = {f"{e['name']}@{e['sensor']}": e for e in j["diagnosis"]["effects"]}
        va, vb = dict(_numbers(ja)), dict(_numbers(jb))
        worst, where, other = 0.0, None, []
        for k in sorted(set(va) | set(vb)):
            x, y = va.get(k, "<missing>"), vb.get(k, "<missing>")
            if isinstance(x, (int, float)) and isinstance(y, (int, float)) and not isinstance(x, bool):
                d = abs(float(x) - float(y))
                if d > worst:
                    worst, where = d, k
            elif x != y:
                other.append((k, x, y))
        da, db = ja["diagnosis"], jb["diagnosis"]
        same2 = [k for k, e in da["effects"].items() if e["stage"] == 2 and db["effects"].get(k, {}).get("stage") == 2]
        d2 = max((abs(float(va[p]) - float(vb[p])) for p in va if any(p.startswith(f".diagnosis.effects.{k}.")
                  for k in same2) and isinstance(va[p], (int, float)) and isinstance(vb.get(p), (int, float))), default=0.0)
        print(f"{fa.name}: {len(same2)} candidates refitted in both, max |Δ| of their numbers {d2:.3g}; verdict {da['verdict']}/{da['sensor']} vs {db['verdict']}/{db['sensor']}; "
              f"{len(va)} values, max |Δ number| {worst:.3g} at {where}; {len(other)} non-numeric differences"
              + (f" (first: {other[0]})" if other else ""))
        n_diff += (worst > 0) + len(other)
    print(f"{n_diff} case(s)/values differing")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hosts", default=",".join(HOSTS))
    p.add_argument("--labels", default=",".join(LABELS))
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="diagnose_body.json")
    p.add_argument("--absorption", default=None, metavar="SENSOR",
                   help="instead of the harness: how much of an injected drift / acc bias on SENSOR the base "
                        "fit absorbs, per host (docs/diagnose_body.md §3)")
    p.add_argument("--diagnose-hosts", default=None,
                   help="diagnose only these of --hosts; the others' cases are drawn but not diagnosed, so the cases "
                        "of the listed hosts are those of the full run")
    p.add_argument("--profile", action="store_true", help="cProfile the harness cases (stats to bench_out/<out>.prof)")
    p.add_argument("--dump-dir", default=None, help="write every case's diagnosis.json into bench_out/DIR")
    p.add_argument("--compare", nargs=2, default=None, metavar=("DIR_A", "DIR_B"))
    p.add_argument("--opt", action="append", default=[], metavar="FIELD=VALUE",
                   help="a BodyDiagnoseOptions field (python literal value), repeatable")
    a = p.parse_args(argv)
    if a.compare:
        return compare(*a.compare)
    options = body_options(a.opt)
    if a.absorption:
        recs = []
        for host in [h for h in a.hosts.split(",") if h]:
            print(f"{host}, {a.absorption}:", flush=True)
            recs += absorption(host, a.absorption, a.duration, a.seed)
        print(f"wrote {write_json(a.out, {'issue': '5 (body) absorption', 'args': vars(a), 'records': recs})}")
        return 0
    rng = np.random.default_rng(a.seed)
    records = []
    dump = Path(a.dump_dir) if a.dump_dir else None
    prof = None
    if a.profile:
        import cProfile
        prof = cProfile.Profile(time.process_time)          # CPU time, not wall (shared machine)
    for host in [h for h in a.hosts.split(",") if h]:
        base = host_session(host, a.duration, a.seed)
        diagnose = a.diagnose_hosts is None or host in a.diagnose_hosts.split(",")
        print(f"{host}: {len(base.sensors)} sensors, {base.n} samples, {base.rate:.0f} Hz"
              + ("" if diagnose else " (drawn, not diagnosed)"), flush=True)
        for label in [x for x in a.labels.split(",") if x]:
            if prof is not None:
                prof.enable()
            rec = run_case(host, base, label, rng, options, dump, diagnose=diagnose)
            if rec is not None:
                records.append(rec)
            if prof is not None:
                prof.disable()
    if prof is not None:
        import pstats

        from benchmarks.output import OUT_DIR
        OUT_DIR.mkdir(exist_ok=True)
        prof.dump_stats(str(OUT_DIR / (Path(a.out).stem + ".prof")))
        st = pstats.Stats(prof)
        st.sort_stats("cumulative").print_stats(35)
        st.sort_stats("tottime").print_stats(20)
    s = summary(records)
    print("\nconfusion (rows: injected, columns: verdict)")
    print(f"{'':<20}" + "".join(f"{c[:12]:>13}" for c in LABELS))
    for r in LABELS:
        print(f"{r:<20}" + "".join(f"{s['confusion'][r][c]:>13}" for c in LABELS))
    print(f"top-1 (effect and sensor) on injected cases: {s['top1_effect_and_sensor']:.2f}; "
          f"none on clean simulations: {s['none_on_clean_simulations']:.2f}; window IoU {np.round(s['window_iou'], 2)}; "
          f"median held-out shrink (correct): {s['median_shrink_correct']}")
    real = [r for r in records if r["host"] == "real_walk" and r["label"] == "none"]
    for r in real:
        lt = r["soft_tissue_per_sensor"].get("LeftUpperLeg", {})
        print(f"real walk, nothing injected: verdict {r['verdict']} ({r['sensor']}), {r['seconds']:.1f} s; "
              f"left thigh gaps {({c: round(v['gap'], 2) for c, v in r['gaps']['LeftUpperLeg'].items()})}; "
              f"left thigh soft_tissue: G {lt.get('loglik_gain', float('nan')):+.3f}, shrink "
              f"{lt.get('shrink', float('nan')):.2f}, size {lt.get('size')}, significant {lt.get('significant')}, "
              f"relevant {lt.get('relevant')}, stage {lt.get('stage')}")
    print(f"CPU per case: {[round(r['cpu_s'], 1) for r in records]} s, total {sum(r['cpu_s'] for r in records):.1f} s")
    path = write_json(a.out, {"issue": "5 (body)", "args": vars(a), "summary": s, "records": records})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
