"""Helper L22: the fixed lag with default options is bit-identical to the committed (HEAD) body_incremental.py.

Loads `git show HEAD:imugraph/graphs/body_incremental.py` as a separate module (read-only git), solves one simulated
session with both (default BodyOptions, lag 1 s, auto bootstrap) and compares the outputs (smoothed and filtered).

    .venv/bin/python benchmarks/l22_default_check.py [--motion cmu131_02] [--seed 1] [--mag]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.body_bench import simulated_session  # noqa: E402


def main(argv=None) -> int:
    from imugraph.graphs.body_incremental import solve_body_incremental
    from imugraph.graphs.body_model import BodyOptions

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motion", default="cmu131_02")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--mag", action="store_true")
    a = ap.parse_args(argv)
    src = subprocess.run(["git", "show", "HEAD:imugraph/graphs/body_incremental.py"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    with tempfile.NamedTemporaryFile("w", suffix="_head_body_incremental.py", delete=False) as f:
        f.write(src)
    spec = importlib.util.spec_from_file_location("head_body_incremental", f.name)
    head = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(head)
    os.unlink(f.name)
    _, sess, _ = simulated_session(a.motion, a.seed)
    opts = BodyOptions(use_mag=a.mag)
    new = solve_body_incremental(sess, opts, lag_s=1.0)
    old = head.solve_body_incremental(sess, opts, lag_s=1.0)
    same = {"smoothed n_quat": np.array_equal(new.n_quat, old.n_quat), "smoothed n_pos": np.array_equal(new.n_pos, old.n_pos),
            "filtered n_quat": np.array_equal(new.info["filtered"].n_quat, old.info["filtered"].n_quat),
            "filtered n_pos": np.array_equal(new.info["filtered"].n_pos, old.info["filtered"].n_pos)}
    print(f"{a.motion} s{a.seed} {'mag' if a.mag else 'no-mag'} lag 1: identical to HEAD: {same}")
    return 0 if all(same.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
