"""Terminating events in the step that reaches `t1`: an ensemble member whose event fires
between its last step's start and `t1` ends at the event, in every mode (a defect of the batch
engine: the step clipped to `t1` was accepted as completed, the rod past the floor)."""

import numpy as np
import pytest

import jaxdyn as jd

ROD = jd.Scene(jd.FallingRod(length=1.0, mass=1.0, g=9.81))
THETA0 = np.linspace(0.1, 0.5, 8)


@pytest.mark.parametrize("mode", ["adaptive", "vmap"])
@pytest.mark.parametrize("margin", [1e-6, 1e-2])
def test_event_in_the_last_step_ends_the_run(mode, margin):
    # Independent route: fall times by quadrature of the energy integral.
    fall = np.array([float(ROD.body.fall_time(th, 0.0)) for th in THETA0])
    t1 = fall[3] * (1 + margin)  # just after the fourth rod lies flat, before the first three
    res = jd.ensemble(ROD, {"theta": THETA0, "theta_dot": np.zeros(8)}, t1, mode=mode,
                      observe=lambda tr: {"t_final": tr.t_final, "theta": tr.y_final["theta"]})
    falls = fall <= t1
    assert falls[3:].all() and not falls[:3].any()
    names = np.array([res.status_names[s] for s in res.status])
    assert (names[falls] == "event").all(), names
    assert (names[~falls] == "completed").all(), names
    assert np.allclose(res.values["t_final"][falls], fall[falls], rtol=1e-7, atol=0)
    assert np.allclose(np.abs(res.values["theta"][falls]), np.pi / 2, atol=1e-12)
    assert np.all(res.values["t_final"][~falls] == t1)
    assert np.all(np.abs(res.values["theta"][~falls]) < np.pi / 2)
