"""Body-session attribution (imugraph.diagnose.body.run): a clean simulated walk comes out "none", a soft-tissue
wobble injected into one thigh sensor comes out soft_tissue on that sensor; the report keeps the DESIGN.md keys.
Sessions from tests/test_diagnose_body.py's analytic lower-body motion (independent of the BVH data)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_diagnose_body import _session  # noqa: E402

from imugraph.diagnose.body.effects.soft_tissue import EFFECT as SOFT  # noqa: E402
from imugraph.diagnose.body.run import BodyDiagnoseOptions, diagnose_body  # noqa: E402


@pytest.fixture(scope="module")
def clean():
    return _session(11.0, seed=0)


def test_clean_session_is_none_and_soft_tissue_is_found_on_its_sensor(clean, tmp_path):
    d0 = diagnose_body(clean, BodyDiagnoseOptions(seed=0, effects=("soft_tissue", "accelerometer_bias")))
    assert d0.verdict == "none", [(e["name"], e["sensor"], e["loglik_gain"], e["shrink"]) for e in d0.effects[:3]]
    rng = np.random.default_rng(4)
    inj, truth = SOFT.inject(clean, rng, sensor="LeftUpperLeg", strength=0.02)
    assert truth["sensor"] == "LeftUpperLeg" and truth["params"]["displacement_rms_m"] > 0.001
    d1 = diagnose_body(inj, BodyDiagnoseOptions(seed=0, effects=("soft_tissue", "accelerometer_bias")))
    assert (d1.verdict, d1.sensor) == ("soft_tissue", "LeftUpperLeg")
    best = d1.effects[0]
    assert best["shrink"] > 0.25 and best["loglik_gain"] > 0
    from imugraph.diagnose.body.report import write_report
    paths = write_report(d1, tmp_path)
    js = json.loads((tmp_path / "diagnosis.json").read_text())
    assert js["verdict"] == "soft_tissue" and js["sensor"] == "LeftUpperLeg"
    assert set(js["gap"]) >= {"gyr", "acc", "mag"} and js["effects"][0]["sensor"] == "LeftUpperLeg"
    assert all(k in js["effects"][0] for k in ("name", "channel", "t_start", "t_end", "gap_before", "gap_after",
                                                 "shrink", "params"))
    assert set(paths) == {"diagnosis.json", "diagnosis.md", "gap_over_time.png", "residuals.png"}
