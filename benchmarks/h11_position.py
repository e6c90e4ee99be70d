"""H11 (issue 2c): the bounded-position option (Options.position_sigma, graphs/velocity_block.py (P1)) against the
defaults on the BROAD trials, every variant in the same run, beside offline VQF (cached as in h4_decompose).

    .venv/bin/python benchmarks/h11_position.py [TRIALS] --variant "position_sigma=1.0" \
        [--variant "position_sigma=1.0;field_tau=3.0" ...]

Each --variant is a ';'-separated list of Options FIELD=VALUE; the defaults are always run first ("base").
Per trial: total RMS error (°, scored as broad_published.py: movement, best shift ±3 samples, best constant
heading) and inclination/heading; calibrate CPU s. Summary per variant: 17-trial mean, trials behind offline VQF,
the largest loss against base. Writes bench_out/h11_position.json.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.b1_try import vqf_cached  # noqa: E402
from benchmarks.common import error_parts, iter_broad, parse_options, parse_variants  # noqa: E402
from benchmarks.h4_decompose import CACHE  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks._usage import check_trials, exit_on_help  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402


def _sigma(row: dict, name: str) -> str:
    """", σp X" when the variant ran with a position state (Estimate.info["position_sigma"]), ", σd,y Y" the final
    solve's cross-field σ of the field perturbation (Estimate.info["final_field_sigma"]); else ""."""
    v, fy = row.get(name + "_sigma_p"), row.get(name + "_field_y")
    return ("" if v is None else f", σp {v:.3g}") + ("" if fy is None else f", σd,y {fy:.3g}")


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--variant",), max_args=1)
    variants, rest = parse_variants(argv)
    select = set(rest[0].split(",")) if rest else None
    check_trials(select)
    rows = []
    for num, s, mask in iter_broad(select):
        q_v = vqf_cached(num, s, CACHE)
        row = {"trial": num, "offline_vqf": error_parts(q_v, s, mask)}
        for name, opts in variants.items():
            t0 = time.process_time()
            est = calibrate(s, parse_options(opts), allow_weak=True)
            row[name] = error_parts(est.quat, s, mask)
            row[name + "_cpu"] = time.process_time() - t0
            row[name + "_sigma_p"] = est.info.get("position_sigma")     # chosen / estimated σ_p (task J)
            row[name + "_select"] = [{k: h[k] for k in ("position_select", "position_select_field") if k in h}
                                     for h in est.info.get("history", []) if "position_select" in h
                                     or "position_select_field" in h]   # the (J2) scores (task J2)
            fs = est.info.get("final_field_sigma")
            row[name + "_field_y"] = None if fs is None else float(np.broadcast_to(np.asarray(fs, float), (3,))[1])
        rows.append(row)
        print(f"{num} VQF {row['offline_vqf'][0]:.3f} | " + " | ".join(
            f"{n} {row[n][0]:.3f} (i {row[n][1]:.3f} h {row[n][2]:.3f}, {row[n + '_cpu']:.1f} s{_sigma(row, n)})"
            for n in variants),
            flush=True)
    if not rows:
        return 2
    for n in variants:
        tot = np.array([r[n][0] for r in rows])
        vqf = np.array([r["offline_vqf"][0] for r in rows])
        base = np.array([r["base"][0] for r in rows])
        behind = [r["trial"] for r, a, b in zip(rows, tot, vqf) if a > b]
        j = int(np.argmax(tot - base))
        print(f"[{n}] mean {tot.mean():.3f} (offline VQF {vqf.mean():.3f}); behind offline VQF {len(behind)}: "
              f"{','.join(behind)}; largest loss vs base {tot[j] - base[j]:+.3f} ({rows[j]['trial']}); "
              f"CPU {min(r[n + '_cpu'] for r in rows):.2f}–{max(r[n + '_cpu'] for r in rows):.2f} s")
    write_json("h11_position.json", {"variants": variants, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
