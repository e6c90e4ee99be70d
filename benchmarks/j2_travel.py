"""Task J (issue 2c): does a bounded position hurt a sensor that TRAVELS? Simulated sessions with known truth.

    .venv/bin/python benchmarks/j2_travel.py [SEEDS] [--kind hand,walk,drive] --variant "position_sigma=1.0" \
        --variant "estimate_position_sigma=True" ...

Each session: imugraph.sim's random rotations about all axes (180 s, 100 Hz, rests at both ends and 2 pauses),
a distorted magnetometer, gyro bias and noise exactly as `sim.scenario.distorted_session`, plus a translation:

- hand:  the simulator's own smooth random translation, 0.3 m RMS (a hand within reach);
- walk:  a wandering path at ≈ 1.3 m/s (heading a slow random walk, speed ramps at the rests) with a 2 Hz,
         3 cm vertical bounce: ≈ 200 m of travel;
- drive: ≈ 8 m/s along a wandering path with accelerations up to ≈ 2 m/s²: ≈ 1.3 km.

The sensor rests (no translation) where the rotation rests. Per session: RMS orientation / inclination / heading
error (°) against the simulated truth over the whole motion (evaluate.orientation_error: best constant heading
removed as for BROAD), the estimated σ_p where it is estimated, and the spread of the true path. The defaults
("base") are always run first. Writes bench_out/j2_travel.json.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import error_parts, parse_options, parse_variants  # noqa: E402
from benchmarks.output import write_json  # noqa: E402
from benchmarks._usage import exit_on_help, usage_error  # noqa: E402
from imugraph.calibration.ml import calibrate  # noqa: E402
from imugraph.sim.distortion import random_distortion  # noqa: E402
from imugraph.sim.motion import random_rotation_motion, _rest_envelope, _rest_intervals  # noqa: E402
from imugraph.sim.sensors import SensorParams, simulate_imu  # noqa: E402

DURATION_S, RATE_HZ = 180.0, 100.0


def _smooth_noise(n: int, rate: float, corr_s: float, rng: np.random.Generator) -> np.ndarray:
    """(n,) zero-mean unit-RMS noise smoothed by a Gaussian of `corr_s` seconds."""
    x = rng.standard_normal(n + 1)
    w = int(max(1, 3 * corr_s * rate))
    k = np.exp(-0.5 * (np.arange(-w, w + 1) / (corr_s * rate)) ** 2)
    y = np.convolve(x, k / k.sum(), mode="same")[:n]
    return y / max(np.std(y), 1e-12)


def travel_path(kind: str, t: np.ndarray, env: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) nav-frame positions of a travelling sensor (walk / drive), at rest where env = 0."""
    n, rate = len(t), 1.0 / (t[1] - t[0])
    if kind == "walk":
        speed = 1.3 * env * (1.0 + 0.1 * _smooth_noise(n, rate, 5.0, rng))
        heading = np.cumsum(0.25 * _smooth_noise(n, rate, 3.0, rng)) / rate      # ≈ 0.25 rad/s turns
        bounce = 0.03 * np.sin(2 * np.pi * 2.0 * t) * env
    else:                                                                        # drive
        speed = 8.0 * env * (1.0 + 0.25 * _smooth_noise(n, rate, 8.0, rng))
        heading = np.cumsum(0.08 * _smooth_noise(n, rate, 6.0, rng)) / rate
        bounce = 0.01 * _smooth_noise(n, rate, 0.3, rng) * env
    v = np.stack([speed * np.cos(heading), speed * np.sin(heading), np.zeros(n)], axis=1)
    p = np.cumsum(v, axis=0) / rate
    p[:, 2] += bounce
    return p


def travel_session(seed: int, kind: str, duration_s: float = DURATION_S):
    """A simulated session (distorted_session's sensor) with translation `kind`; returns (session, path)."""
    rng = np.random.default_rng(seed)
    hand = 0.3 if kind == "hand" else 0.0
    t, nRb, b_omega, n_acc = random_rotation_motion(duration_s, RATE_HZ, rng, rest_s=2.0, pauses=2,
                                                    translation_m=hand)
    A, b = random_distortion(rng, 50.0)
    dip_rad = float(np.deg2rad(rng.uniform(40.0, 75.0)))
    gyro_bias = np.deg2rad(rng.choice([-1.0, 1.0], 3) * rng.uniform(0.3, 0.7, 3))
    noise = {"gyr": np.full(3, 0.01), "acc": np.full(3, 0.05), "mag": np.full(3, 0.5)}
    dt = t[1] - t[0]
    if kind in ("walk", "drive"):
        rests = _rest_intervals(t[-1], 2.0, 2, 1.5)
        env = _rest_envelope(t, rests + np.array([-1.5 * dt, 1.5 * dt]), 3.0)   # 3 s speed ramps
        p = travel_path(kind, t, env, np.random.default_rng(seed + 1000))
        n_acc = np.zeros_like(p)
        n_acc[1:-1] = (p[2:] - 2.0 * p[1:-1] + p[:-2]) / dt**2                  # as sim.motion._translation_acc
    else:
        p = np.cumsum(np.cumsum(n_acc, axis=0) * dt, axis=0) * dt
    params = SensorParams(gyro_bias=gyro_bias, gyro_noise=noise["gyr"], acc_noise=noise["acc"],
                          mag_D=A, mag_o=b, dip_rad=dip_rad, field_norm=50.0, mag_noise=noise["mag"])
    return simulate_imu(t, nRb, b_omega, n_acc, params, rng, name=f"j2_{kind}_{seed}"), p


def main(argv: list[str]) -> int:
    exit_on_help(__doc__, argv, flags=("--variant", "--kind"), max_args=1)
    variants, rest = parse_variants(argv)
    kinds = ["hand", "walk", "drive"]
    while "--kind" in rest:                       # the last --kind wins, as before
        i = rest.index("--kind")
        kinds = rest[i + 1].split(",")
        del rest[i:i + 2]
    if rest and not all(x.isdigit() for x in rest[0].split(",")):
        usage_error(f"SEEDS {rest[0]!r}: expected comma-separated integers like 1,2")
    if not set(kinds) <= {"hand", "walk", "drive"}:
        usage_error(f"--kind {','.join(kinds)!r}: expected hand, walk and/or drive")
    seeds = [int(x) for x in rest[0].split(",")] if rest else [1, 2]
    rows = []
    for kind in kinds:
        for seed in seeds:
            s, p = travel_session(seed, kind)
            spread = float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))
            row = {"kind": kind, "seed": seed, "path_m": float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))),
                   "spread_m": spread}
            for name, opts in variants.items():
                t0 = time.process_time()
                est = calibrate(s, parse_options(opts), allow_weak=True)
                row[name] = error_parts(est.quat, s, s.movement)
                row[name + "_cpu"] = time.process_time() - t0
                row[name + "_sigma_p"] = est.info.get("position_sigma")
            rows.append(row)
            print(f"{kind} {seed} path {row['path_m']:.0f} m spread {spread:.1f} m | " + " | ".join(
                f"{n} {row[n][0]:.3f} (i {row[n][1]:.3f} h {row[n][2]:.3f}; σp "
                f"{'-' if row[n + '_sigma_p'] is None else format(row[n + '_sigma_p'], '.3g')}; "
                f"{row[n + '_cpu']:.1f} s)" for n in variants), flush=True)
    for kind in kinds:
        sub = [r for r in rows if r["kind"] == kind]
        print(f"[{kind}] " + "; ".join(
            f"{n}: mean {np.mean([r[n][0] for r in sub]):.3f}°, worst vs base "
            f"{max(r[n][0] - r['base'][0] for r in sub):+.3f}°" for n in variants))
    write_json("j2_travel.json", {"variants": variants, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
