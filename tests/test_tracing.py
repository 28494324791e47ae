"""What the tracing of a run costs, not what it computes: the solver's step is traced once per
`diffrax.diffeqsolve` (`jaxdyn._solvers._wrapped.TracedOnce`), into the very program that
diffrax builds without it; and the command's process defers CPython's full garbage
collections (`jaxdyn._cli._defer_full_collections`) where a caller's process is left alone."""

import gc
import subprocess
import sys

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn as jd
from jaxdyn import _hybrid
from jaxdyn._cli import main

ROD = jd.Scene(jd.FallingRod(length=1.0, mass=1.0, g=9.81))
FREE = jd.Scene(jd.RigidBody(jnp.array([1.0, 2.0, 3.0])))
CASES = {
    # an event and its root find, the default adjoint
    "rod": (ROD, ROD.state(theta=0.3, theta_dot=0.0), 5.0, {}),
    # samples saved at given times (the step reports to the controller: `Reporting`)
    "samples": (FREE, FREE.state(omega=[0.3, 1.0, 0.2]), 6.0, {"ts": jnp.linspace(0, 6, 5)}),
    # an implicit solver, whose root finder takes the controller's tolerances
    "implicit": (FREE, FREE.state(omega=[0.3, 1.0, 0.2]), 3.0, {"solver": dfx.Kvaerno5()}),
    # adjoints for which diffrax picks the Runge-Kutta stage loop itself
    "direct": (FREE, FREE.state(omega=[0.3, 1.0, 0.2]), 3.0,
               {"adjoint": dfx.DirectAdjoint(), "max_steps": 4096}),
    "forward": (FREE, FREE.state(omega=[0.3, 1.0, 0.2]), 3.0, {"adjoint": dfx.ForwardMode()}),
}
# The cases also differentiated here: reverse mode through `DirectAdjoint`'s loop, forward
# mode (as the fits' Jacobians are). The default adjoint's gradients through the wrapped step
# are checked against finite differences elsewhere (test_rod, test_hard_cases, ...).
GRADIENTS = {"direct": jax.grad, "forward": jax.jacfwd}


def _steps_traced(monkeypatch):
    """A counter of the solvers' steps traced from here on."""
    count = [0]
    for cls in (dfx.AbstractRungeKutta,):
        step = cls.step

        def counted(self, *args, _step=step, **kwargs):
            count[0] += 1
            return _step(self, *args, **kwargs)

        monkeypatch.setattr(cls, "step", counted)
    return count


def _final(scene, y0, t1, kw, derivative):
    """The final state, and its gradient with respect to the initial state, from programs
    traced afresh (under the caller's `jit`: nothing read from the program store)."""
    def f(y):
        return jd.simulate(scene, y, t1, **kw).y_final

    def g(y):
        return sum(jnp.sum(v) for v in jax.tree.leaves(f(y)))

    return jax.jit(f)(y0), jax.jit(derivative(g))(y0) if derivative else None


@pytest.mark.optimized  # (two programs compared bit for bit, as a user's are compiled)
@pytest.mark.parametrize("case", list(CASES))
def test_the_step_is_traced_once_into_the_same_program(case, monkeypatch):
    scene, y0, t1, kw = CASES[case]
    count = _steps_traced(monkeypatch)
    jax.clear_caches()  # (traced afresh: JAX's caches hold the programs of earlier tests)
    jax.jit(lambda y: jd.simulate(scene, y, t1, **kw).y_final).trace(y0)
    assert count[0] == 1
    once = _final(scene, y0, t1, kw, GRADIENTS.get(case))
    monkeypatch.setattr(_hybrid, "TracedOnce", lambda solver: solver)  # diffrax's own tracing
    monkeypatch.setattr(_hybrid, "_STAGE_LOOPS", {})  # (and its own choice of stage loop)
    count[0] = 0
    jax.clear_caches()
    jax.jit(lambda y: jd.simulate(scene, y, t1, **kw).y_final).trace(y0)
    assert count[0] >= 3  # (the positive control: diffrax traces it again and again)
    plain = _final(scene, y0, t1, kw, GRADIENTS.get(case))
    for a, b in zip(jax.tree.leaves(once), jax.tree.leaves(plain), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.skipif(sys.version_info >= (3, 14),
                    reason="CPython 3.14's incremental collector has no generation-2 threshold")
def test_the_command_defers_full_collections_and_main_leaves_them_alone():
    before = gc.get_threshold()
    try:
        gc.set_threshold(700, 10, 10)  # (the suite's workers defer them: conftest.py)
        with pytest.raises(SystemExit):
            main(["scenes", "--bogus-option"])  # (exits 2 before any work)
        assert gc.get_threshold() == (700, 10, 10)
    finally:
        gc.set_threshold(*before)
    # The console script's entry, its command and its end replaced: the thresholds it runs under.
    code = ("import gc; from jaxdyn import _cli; gc.set_threshold(700, 10, 10); "
            "_cli.main = lambda: 0; _cli._end = lambda status: print(*gc.get_threshold()); "
            "_cli.console()")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["700", "10", str(1 << 30)]
