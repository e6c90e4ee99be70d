"""Session 23 (helper D23): the body diagnosis's speed options and its N-pose refusal (docs/diagnose_body.md
"Session 23, helper D23").

- `simulate.generator_values` (BodyDiagnoseOptions.sim_start="generator"): the simulations' LM start made
  consistent with the readings the simulation integrated — its start cost far below `warm_values`', the same
  optimum reached.
- `lm.lm_optimize` (BodyDiagnoseOptions.lm_lambda): the same graph solved with a smaller damping floor reaches
  the default LM's optimum (cost no higher, orientations within a fraction of a degree).
- `run.check_npose` / `imugraph diagnose`: a body session without a rest at its start is refused with one line
  that names --npose; the window given with --npose is accepted.
Sessions: the analytic lower-body walk of tests/test_diagnose_body.py (2 s N-pose, then motion).
"""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest

from imugraph.diagnose.body.fit import fit_body
from imugraph.diagnose.body.simulate import (fit_options, fit_simulation, generator_values, simulate_from_fit,
                                             warm_values)
from imugraph.errors import SessionError
from tests.test_diagnose_body import _session


def _rot_diff_deg(a, b) -> float:
    """Largest angle between the per-sample segment orientations of two body results, degrees."""
    from imugraph.geometry import quat_to_rotmat
    Ra, Rb = quat_to_rotmat(np.asarray(a.n_quat, float)), quat_to_rotmat(np.asarray(b.n_quat, float))
    c = (np.einsum("...ji,...ji->...", Ra, Rb) - 1.0) / 2.0
    return float(np.rad2deg(np.arccos(np.clip(c, -1.0, 1.0))).max())


def _drop_start(session, seconds: float):
    """The session without its first `seconds` (every per-sample array cut): it starts in motion."""
    t = np.asarray(session.t, float)
    i0 = int(np.searchsorted(t, t[0] + seconds))

    def cut(obj):
        ch = {f.name: getattr(obj, f.name)[i0:] for f in fields(obj)
              if isinstance(getattr(obj, f.name), np.ndarray) and getattr(obj, f.name).shape[:1] == (t.size,)}
        return replace(obj, **ch)

    return replace(cut(session), sensors={k: cut(v) for k, v in session.sensors.items()}, truth=None)


@pytest.fixture(scope="module")
def real():
    return fit_body(_session(11.0, seed=0))


def test_generator_start_is_consistent_and_reaches_the_same_fit(real):
    from imugraph.graphs.body import build_problem, full_graph

    sim = simulate_from_fit(real, np.random.default_rng(3), "+A")
    pb = build_problem(sim, fit_options(real))
    g = full_graph(pb)
    e_gen, e_sol = g.error(generator_values(sim, real, pb)), g.error(warm_values(real, pb))
    assert e_gen < 0.1 * e_sol, (e_gen, e_sol)
    a_sol = fit_simulation(sim, real, start="solution")
    a_gen = fit_simulation(sim, real, start="generator")
    assert a_gen.info["start"] == "generator" and a_sol.info["start"] == "solution"
    assert a_gen.info["cost_final"] <= 1.01 * a_sol.info["cost_final"]
    assert _rot_diff_deg(a_gen.result, a_sol.result) < 0.5


def test_lm_lambda_reaches_the_default_optimum(real):
    fast = fit_body(real.session, lm=(1e-4, 1e-9))
    assert fast.info["lm"] == (1e-4, 1e-9) and "lm" not in real.info
    # both stop at a relative decrease < 1e-3 (BodyOptions.relative_tol): optima equal to ≈ 1 %
    assert fast.info["cost_final"] <= 1.01 * real.info["cost_final"]
    assert _rot_diff_deg(fast.result, real.result) < 0.5
    sim = fit_simulation(simulate_from_fit(fast, np.random.default_rng(4), "+A"), fast)
    assert sim.info["lm"] == (1e-4, 1e-9)                 # the simulations solve like the recording


def test_session_without_rest_at_start_is_refused_and_npose_accepted():
    from imugraph.diagnose.body.run import check_npose
    from imugraph.graphs.body_model import BodyOptions

    full = _session(9.0, seed=2)
    check_npose(full)                                     # the N-pose at the start: accepted
    moving = _drop_start(full, 4.0)                       # N-pose (2 s) and blend (1 s) cut off
    with pytest.raises(SessionError, match="--npose"):
        check_npose(moving)
    check_npose(moving, BodyOptions(npose=(4.5, 5.5)))    # a given window: accepted (not checked for rest)


def test_cli_refuses_body_session_in_motion_with_one_line(tmp_path, capsys):
    from imugraph.cli import main
    from imugraph.io.body_session import write_body_session

    folder = tmp_path / "moving"
    write_body_session(folder, _drop_start(_session(9.0, seed=2), 4.0))
    rc = main(["diagnose", str(folder), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--npose" in err[0] and "npose" in err[0], err
    assert not (tmp_path / "out").exists()
    rc = main(["diagnose", str(folder), "--out", str(tmp_path / "out"), "--quiet", "--npose", "3,2"])
    assert rc == 2 and "T0 < T1" in capsys.readouterr().err


def test_qmt_full_body_mat_is_a_body_session():
    from pathlib import Path

    from imugraph.commands.diagnose import _is_body_session
    from imugraph.config import data_dir

    path = data_dir() / "qmt_full_body" / "full_body_example_data.mat"
    if not path.exists():
        pytest.skip("qmt full-body file not in the data directory")
    assert _is_body_session(Path(path))
