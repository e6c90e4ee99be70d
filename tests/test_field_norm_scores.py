"""The CLI's field-norm score (commands.common.field_norm_scores) applies the calibration's disturbance windows:
a modelled window's offset is removed before the norm is scored, as the model sees the field."""

from dataclasses import replace

import numpy as np

from imugraph.commands.common import field_norm_scores
from imugraph.sim.scenario import distorted_session


def test_a_modelled_window_is_scored_as_the_model_sees_it():
    session, truth = distorted_session(3, 30.0, 50.0)
    cal = truth.to_calibration()
    scale = float(np.cbrt(abs(np.linalg.det(cal.D))))
    delta = scale * np.array([0.3, -0.25, 0.35])                  # an attached magnet over the last 20 s
    late = session.t >= session.t[0] + 10.0
    mag = session.mag.copy()
    mag[late] += delta
    s = session.with_mag(mag)
    clean_after = field_norm_scores(session, cal)[1]
    plain_after = field_norm_scores(s, cal)[1]                      # the magnet counted as calibration error
    window = {"t_start": float(s.t[late][0]), "t_end": float(s.t[-1]), "offset": delta.tolist(),
              "modelled": True, "left_out": []}
    modelled_after = field_norm_scores(s, replace(cal, disturbances=[window]))[1]
    unexplained_after = field_norm_scores(s, replace(cal, disturbances=[dict(window, modelled=False)]))[1]
    assert plain_after > 5 * clean_after
    assert abs(modelled_after - clean_after) < 0.1 * clean_after + 1e-4
    assert unexplained_after < 0.5 * plain_after                    # its samples are not scored
