"""The torque-free body and its effects, checked against scipy integrations, closed forms and
conservation laws."""

from functools import partial

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    FINITE_DIFF,
    INTEGRATION,
    ROUNDOFF,
    central_difference,
    expm_longdouble,
    new_programs,
    scipy_euler,
    tol,
)
from scipy.spatial.transform import Rotation

import jaxdyn as jd

TIGHT = dict(rtol=1e-12, atol=1e-13)
# Simulation against the closed form through flips of a spin about the intermediate axis: an
# error made near a saddle grows like exp(sigma t) until the next one, so at rtol = 1e-12 the
# rates agree only to 2e-9..1e-7 of the rate 2 (the round-off of each run decides where: the
# largest error over ten initial conditions 5% apart, measured at 069c366 and after).
FLIPS = 2e-7


def _random_bodies(n, seed):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        inertia = rng.uniform(0.5, 3.0, 3)
        if inertia.max() <= inertia.sum() - inertia.max():
            out.append((inertia, rng.normal(size=3)))
    return out


@pytest.mark.parametrize("inertia, omega0", _random_bodies(6, 0))
def test_exact_solution_matches_scipy_integration(inertia, omega0):
    ts = np.linspace(0, 20, 201)
    exact = jd.torque_free_omega(jnp.asarray(inertia), jnp.asarray(omega0), jnp.asarray(ts))
    assert np.allclose(exact, scipy_euler(inertia, omega0, ts[-1], ts), atol=1e-10)


@pytest.mark.parametrize("side", [+1, -1, 0])
def test_exact_solution_both_sides_of_separatrix_and_on_it(side):
    inertia = np.array([1.0, 2.0, 3.0])
    # On the separatrix: I1 (I1 - I2) w1^2 + I3 (I3 - I2) w3^2 = 0.
    w1 = 0.5
    w3 = w1 * np.sqrt(1 * (2 - 1) / (3 * (3 - 2))) * (1 + 0.05 * side)
    omega0 = np.array([w1, 0.3, w3])
    assert np.sign(jd.separatrix_condition(inertia, omega0)) == side or side == 0
    ts = np.linspace(0, 15, 151)
    exact = jd.torque_free_omega(jnp.asarray(inertia), jnp.asarray(omega0), jnp.asarray(ts))
    assert np.allclose(exact, scipy_euler(inertia, omega0, ts[-1], ts), atol=1e-9)
    m, m1 = jd.elliptic_parameter(inertia, omega0)
    assert np.isclose(m + m1, 1.0, rtol=tol(ROUNDOFF))
    if side == 0:
        assert abs(float(m1)) < 1e-15


def test_simulate_matches_exact_solution_and_conserves_invariants():
    body = jd.RigidBody([1.0, 2.0, 3.0])
    scene = jd.Scene(body)
    omega0 = jnp.array([0.3, 0.2, 1.0])
    ts = jnp.linspace(0, 50, 101)
    traj = jd.simulate(scene, scene.state(omega=omega0), 50.0, ts=ts, **TIGHT)
    assert np.allclose(traj.omega, body.exact_omega(omega0, ts), atol=tol(INTEGRATION))
    for name in ("energy", "momentum"):
        v = np.asarray(getattr(traj, name))
        assert np.max(np.abs(v / v[0] - 1)) < tol(INTEGRATION)
    assert scene.conserved == ("energy", "momentum")


def test_attitude_keeps_inertial_momentum_and_unit_quaternion():
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]), attitude=True)
    q0 = jnp.array([0.9, 0.1, -0.3, 0.2])
    y0 = scene.state(omega=[0.3, 1.5, 0.4], quaternion=q0)
    traj = jd.simulate(scene, y0, 30.0, ts=jnp.linspace(0, 30, 61), **TIGHT)
    h_n = np.asarray(traj.momentum_inertial)
    assert np.max(np.linalg.norm(h_n - h_n[0], axis=1)) < 1e-9 * np.linalg.norm(h_n[0])
    assert np.max(np.abs(np.asarray(traj.quaternion_norm) - 1)) < 1e-10
    assert "momentum_inertial" in scene.conserved


def test_intermediate_axis_flips_match_closed_form_and_conserve():
    # Spun almost exactly about the intermediate axis, the body flips over and back (four flips
    # in 60 s): the simulated rates follow the Jacobi-elliptic closed form through every flip,
    # and energy, |H| and the inertial momentum vector stay put.
    body = jd.RigidBody([1.0, 2.0, 3.0])
    scene = jd.Scene(body, attitude=True)
    omega0 = jnp.array([1e-3, 2.0, 1e-3])
    ts = jnp.linspace(0.0, 60.0, 61)  # the shape of the test above: no new compilation
    traj = jd.simulate(scene, scene.state(omega=omega0), 60.0, ts=ts, **TIGHT)
    w = np.asarray(traj.omega)
    assert np.sum(np.sign(w[1:, 1]) != np.sign(w[:-1, 1])) >= 4
    assert np.max(np.abs(w - np.asarray(body.exact_omega(omega0, ts)))) < FLIPS
    for name in ("energy", "momentum"):
        v = np.asarray(getattr(traj, name))
        assert np.max(np.abs(v / v[0] - 1)) < tol(INTEGRATION)
    h_n = np.asarray(traj.momentum_inertial)
    assert np.max(np.linalg.norm(h_n - h_n[0], axis=1)) < tol(INTEGRATION) * np.linalg.norm(h_n[0])


def test_full_tensor_equals_rotated_principal_body():
    moments = np.array([1.0, 2.0, 2.5])
    rot = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    tensor = rot @ np.diag(moments) @ rot.T
    body = jd.RigidBody(tensor)
    got_moments, axes = body.principal_moments, body.principal_axes
    assert np.allclose(got_moments, np.sort(moments), rtol=tol(ROUNDOFF))
    assert np.allclose(axes @ np.diag(got_moments) @ axes.T, tensor, atol=1e-12)
    assert np.isclose(np.linalg.det(axes), 1.0)
    omega0 = np.array([0.4, -1.0, 0.7])
    ts = np.linspace(0, 10, 21)
    scene = jd.Scene(body)
    traj = jd.simulate(scene, scene.state(omega=omega0), 10.0, ts=jnp.asarray(ts), **TIGHT)
    assert np.allclose(traj.omega, scipy_euler(tensor, omega0, ts[-1], ts), atol=1e-9)
    assert np.allclose(body.exact_omega(omega0, ts), scipy_euler(tensor, omega0, ts[-1], ts),
                       atol=1e-10)


def _flips(inertia, omega0, rotor, t1=60.0):
    effects = () if rotor is None else (jd.Rotor(rotor),)
    scene = jd.Scene(jd.RigidBody(inertia), effects)
    traj = jd.simulate(scene, scene.state(omega=omega0), t1, ts=jnp.linspace(0, t1, 601),
                       **TIGHT)
    return traj


def test_gyrostat_conserves_and_rotor_stabilises_intermediate_axis():
    inertia, omega0 = [1.0, 2.0, 3.0], [1e-3, 2.0, 1e-3]
    free = _flips(inertia, omega0, None)
    assert np.min(np.asarray(free.omega)[:, 1]) < -1.9  # flips
    # Spin w about axis 2 with rotor momentum h along it is stable when
    # (I2 w + h - I1 w)(I2 w + h - I3 w) > 0: here h > (I3 - I2) w = 2.
    for h, stable in ((2.5, True), (1.5, False)):
        traj = _flips(inertia, omega0, [0.0, h, 0.0])
        w = np.asarray(traj.omega)
        assert (np.min(w[:, 1]) > 1.99) == stable
        for name in ("energy", "momentum"):
            v = np.asarray(getattr(traj, name))
            assert np.max(np.abs(v / v[0] - 1)) < tol(INTEGRATION)
        h_total = np.asarray(traj.angular_momentum)
        assert np.allclose(h_total[0], np.array(inertia) * np.array(omega0) + [0, h, 0])


def test_constant_body_torque_on_a_sphere_is_linear_in_time():
    c = 2.0
    tau = np.array([0.1, -0.2, 0.3])
    scene = jd.Scene(jd.RigidBody([c, c, c]), (jd.ExternalTorque(tau),))
    omega0 = np.array([0.5, 0.1, -0.2])
    traj = jd.simulate(scene, scene.state(omega=omega0), 4.0, **TIGHT)
    assert np.allclose(traj.y_final["omega"], omega0 + tau * 4.0 / c, rtol=1e-11)
    assert scene.conserved == ()


def test_inertial_torque_changes_inertial_momentum_linearly():
    tau_n = jnp.array([0.05, 0.0, -0.02])
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]), (jd.ExternalTorque(tau_n, frame="inertial"),))
    assert scene.attitude
    y0 = scene.state(omega=[0.2, 1.0, -0.3])
    ts = jnp.linspace(0, 10, 11)
    traj = jd.simulate(scene, y0, 10.0, ts=ts, **TIGHT)
    h_n = np.asarray(traj.momentum_inertial)
    assert np.allclose(h_n - h_n[0], np.outer(ts, tau_n), atol=1e-10)


def test_time_dependent_torque():
    scene = jd.Scene(jd.RigidBody([1.5, 1.5, 1.5]),
                     (jd.ExternalTorque(lambda t: jnp.stack([jnp.cos(t), 0.0 * t, 0.0 * t])),))
    traj = jd.simulate(scene, scene.state(omega=[0.0, 0.0, 0.0]), 2.0, **TIGHT)
    assert np.isclose(traj.y_final["omega"][0], np.sin(2.0) / 1.5, rtol=1e-10)


def test_gravity_gradient_torque_is_minus_gradient_of_potential():
    # V = (3 n^2 / 2) o . I o in the body frame; rotating the body by a small angle a about axis
    # k moves o to o - a e_k x o, and the torque about k is -dV/da.
    n = 0.3
    effect = jd.GravityGradient(orbit_rate=n)
    body = jd.RigidBody([1.0, 2.0, 2.5])
    q = jnp.asarray(Rotation.from_rotvec([0.4, -0.2, 0.9]).as_quat()[[3, 0, 1, 2]])
    t = 0.7
    o = effect.direction(t, q)
    torque = effect.torque(t, {"quaternion": q, "omega": jnp.zeros(3)}, {}, body)

    def potential(a, k):
        e = jnp.zeros(3).at[k].set(1.0)
        o_rot = o - a * jnp.cross(e, o)
        return 1.5 * n**2 * o_rot @ (body.inertia * o_rot)

    minus_grad = jnp.stack([-jax.grad(potential)(0.0, k) for k in range(3)])
    assert np.allclose(torque, minus_grad, rtol=tol(ROUNDOFF), atol=1e-15)


def test_gravity_gradient_equilibrium_stays_put():
    # Smallest axis radial, largest along the orbit normal, rotating once per orbit: a relative
    # equilibrium of the gravity-gradient torque.
    n = 0.01
    scene = jd.Scene(jd.RigidBody([60.0, 80.0, 100.0]), (jd.GravityGradient(n),))
    traj = jd.simulate(scene, scene.state(omega=[0.0, 0.0, n]), 2 * np.pi / n, **TIGHT)
    assert np.allclose(traj.y_final["omega"], [0, 0, n], atol=1e-12)
    q = np.asarray(traj.y_final["quaternion"])
    assert np.isclose(abs(q[0]), 1.0, atol=1e-9)  # one full turn: back to the start


def test_gradient_through_simulation_matches_finite_differences():
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]))

    def loss(x):
        s = scene.replace(inertia=x[:3])
        traj = jd.simulate(s, s.state(omega=x[3:]), 5.0, **TIGHT)
        return jnp.sum(traj.y_final["omega"] ** 2 * jnp.array([1.0, 2.0, 3.0]))

    x = jnp.array([1.0, 2.0, 2.7, 0.3, 0.9, 0.5])
    g = jax.grad(loss)(x)
    fd = central_difference(loss, np.asarray(x), eps=1e-5)
    assert np.allclose(g, fd, rtol=tol(FINITE_DIFF), atol=1e-7)


def test_exact_solution_is_differentiable():
    def f(x):
        return jd.torque_free_omega(x[:3], x[3:], 7.0)[1]

    x = jnp.array([1.0, 2.0, 2.7, 0.3, 1.2, 0.4])  # off the flat-plate boundary I3 = I1 + I2
    fd = central_difference(f, np.asarray(x), eps=1e-6)
    assert np.allclose(jax.grad(f)(x), fd, rtol=tol(FINITE_DIFF), atol=1e-8)


def test_changing_a_parameter_does_not_recompile():
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]))
    y0 = scene.state(omega=[0.1, 1.0, 0.1])
    jd.simulate(scene, y0, 3.0)
    with new_programs() as compiled:
        for inertia in ([1.1, 2.0, 3.0], [1.0, 2.5, 3.1]):
            jd.simulate(scene.replace(inertia=inertia), y0, 4.0)
    assert not compiled
    # Positive control: a change of structure (here the step budget, a static setting no other
    # test uses) is seen to compile a new program.
    with new_programs() as compiled:
        jd.simulate(scene, y0, 4.0, max_steps=54_321)
    assert compiled


@pytest.mark.parametrize("attitude", [False, True])
def test_a_new_number_of_times_reuses_the_closed_forms_program(attitude):
    # The closed forms are evaluated over the times padded to one of a few lengths, so a new
    # number of times (a notebook's slider over the time span) lowers only the small program
    # that cuts the padding off, not the closed form again.
    inertia, omega0 = [1.0, 2.0, 3.0], [0.3, 1.0, 0.2]

    def closed_form(t):
        if attitude:
            return jd.torque_free_attitude(inertia, omega0, [0.5, 0.5, 0.5, 0.5], t)
        return jd.torque_free_omega(inertia, omega0, t)

    from jaxdyn import _free_body, _free_body_attitude

    jitted = (_free_body_attitude._torque_free_attitude if attitude
              else _free_body._torque_free_omega)
    closed_form(np.linspace(0.0, 9.0, 100))
    programs = jitted._cache_size()
    for n in (101, 107, 112):  # padded to 112, as 100 was
        with new_programs() as compiled:
            out = closed_form(np.linspace(0.0, 9.0, n))
        assert len(compiled) == 1 and out.shape == (n, 4 if attitude else 3)  # the cut alone
    assert jitted._cache_size() == programs
    with new_programs() as compiled:  # positive control: past the padded length
        closed_form(np.linspace(0.0, 9.0, 113))
    assert len(compiled) == 2 and jitted._cache_size() == programs + 1

    # The padding changes nothing but round-off (XLA vectorises another length otherwise):
    # every shape of times against the closed form's own program at that exact length, and
    # the times one at a time. Both closed forms pad through the one `over_padded_times`, so
    # the attitude (whose program takes 3-4 s to compile, each length anew) is held to the
    # shapes that exercise its own reshaping of the output (scalar, 2-D, empty).
    roundoff = 16 * np.finfo(np.float64).eps  # (the values are of size one)
    arrays = [jnp.asarray(inertia), jnp.asarray(omega0)]
    program = partial(jitted, *arrays, *([jnp.asarray([0.5] * 4)] if attitude else []))
    shapes = (np.float64(1.3), np.linspace(0.0, 40.0, 35).reshape(5, 7), np.zeros(0))
    if not attitude:
        shapes += (np.linspace(-2.0, 7.0, 17), np.linspace(0.0, 400.0, 1000))
    for t in shapes:
        got, want = closed_form(t), program(jnp.asarray(t))
        assert got.shape == want.shape == t.shape + (4 if attitude else 3,)
        assert np.allclose(got, want, rtol=0, atol=roundoff)
    t = np.linspace(0.0, 20.0, 9)
    assert np.allclose(closed_form(t), np.stack([closed_form(x) for x in t]), rtol=0,
                       atol=roundoff)
    if not attitude:  # under the caller's transformation: its own program, of its length
        assert np.allclose(jax.jit(closed_form)(t), closed_form(t), rtol=0, atol=roundoff)


def test_solver_and_controller_choices():
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]))
    omega0 = jnp.array([0.3, 0.2, 1.0])
    exact = scene.body.exact_omega(omega0, 2.0)
    for kw in (dict(solver=dfx.Dopri8()), dict(solver=dfx.Kvaerno5()),
               dict(solver=dfx.Heun(), stepsize_controller=dfx.ConstantStepSize(), dt0=1e-3)):
        traj = jd.simulate(scene, scene.state(omega=omega0), 2.0, **kw)
        assert np.allclose(traj.y_final["omega"], exact, atol=1e-5)


def test_float32_rigid_body_keeps_dtype():
    body = jd.RigidBody(np.array([1.0, 2.0, 3.0], np.float32))
    scene = jd.Scene(body, (jd.Rotor(np.array([0.0, 0.5, 0.0], np.float32)),), attitude=True)
    traj = jd.simulate(scene, scene.state(omega=np.array([0.1, 1.0, 0.1], np.float32)), 5.0,
                       rtol=1e-5, atol=1e-6)
    assert traj.y_final["omega"].dtype == jnp.float32
    assert traj.y_final["quaternion"].dtype == jnp.float32


@pytest.mark.parametrize("omega0", [[0.0, 0.5, 1.0], [1.0, 0.5, 0.0], [0.3, 0.0, 1.0]])
def test_exact_solution_gradient_when_a_rate_is_zero(omega0):
    # A zero rate on the axis that fixes the phase (axis 1 above the separatrix, axis 3 below)
    # puts the initial phase at a quarter period, where R_F's derivative is infinite; the
    # complementary form keeps the Jacobian right.
    inertia = jnp.array([1.0, 2.0, 3.0])

    def f(w):
        return jd.torque_free_omega(inertia, w, 3.0)

    w0 = jnp.array(omega0)
    jac = np.asarray(jax.jacfwd(f)(w0))
    fd = np.stack([central_difference(lambda w, i=i: f(w)[i], np.asarray(w0), eps=1e-6)
                   for i in range(3)])
    assert np.allclose(jac, fd, rtol=tol(FINITE_DIFF), atol=1e-8)


SPINS = [([2.0, 1.0, 2.5], [0.0, 0.0, 1.2]),  # about the major axis
         ([2.0, 1.0, 2.5], [0.8, 0.0, 0.0]),  # about the intermediate axis (unstable)
         ([2.0, 1.0, 2.5], [0.0, -0.7, 0.0]),  # about the minor axis
         ([1.0, 1.0, 1.8], [0.6, 0.0, 0.0]),  # about a transverse axis of a symmetric body
         ([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])]  # at rest


@pytest.mark.parametrize("inertia, omega0", SPINS)
def test_linearised_flow_of_a_spin_is_the_matrix_exponential(inertia, omega0):
    # The closed form of expm(J t) at a principal-axis spin (Cayley-Hamilton), from t = 0
    # through the series' range (|mu^2 t^2| < 1) to growth by a factor of about 1e6, against
    # the Taylor series scaled and squared in NumPy's long double (64-bit mantissa here), and
    # against jax.scipy.linalg.expm (Pade approximants), which it replaces: that one is off by
    # up to 1e-11 of the largest entry here, its squarings' round-off.
    from jaxdyn._free_body import euler_jacobian, spin_flow

    jac = euler_jacobian(jnp.asarray(inertia), jnp.asarray(omega0))
    ts = jnp.asarray([0.0, 1e-9, 0.05, 0.3, 1.0, 2.2, 7.0, 40.0])
    got = np.asarray(spin_flow(jac, ts))

    want = np.stack([expm_longdouble(np.asarray(jac) * float(t)) for t in ts])
    pade = np.stack([np.asarray(jax.scipy.linalg.expm(jac * t)) for t in ts])
    scale = np.max(np.abs(want), axis=(1, 2), keepdims=True)
    # (Where long double is float64, as on some ARM machines, the reference is only as good.)
    assert np.max(np.abs(got - want) / scale) < (
        1e-14 if np.finfo(np.longdouble).eps < 1e-18 else 1e-11)
    assert np.max(np.abs(pade - want) / scale) < 1e-10  # (the independent route agrees)


@pytest.mark.parametrize("inertia, omega0", SPINS[:4])
def test_exact_rates_at_a_principal_axis_spin_have_the_linearised_derivative(inertia, omega0):
    # At a spin the rates are constant; their derivative with respect to the initial rates is
    # the linearised flow. Against central differences, which perturb the spin off the axis
    # and so go through the general (elliptic) branch of the closed form.
    def f(w):
        return jd.torque_free_omega(jnp.asarray(inertia), w, jnp.asarray([0.0, 3.7, 12.0]))

    w0 = np.asarray(omega0)
    jac = np.asarray(jax.jacfwd(f)(jnp.asarray(w0)))  # (times, 3, 3)
    fd = np.stack([np.stack([central_difference(lambda w, k=k, i=i: f(w)[k, i], w0, eps=1e-6)
                             for i in range(3)]) for k in range(3)])
    assert np.all(np.isfinite(jac))
    np.testing.assert_allclose(jac, fd, rtol=0, atol=tol(FINITE_DIFF) * np.max(np.abs(fd)))


@pytest.mark.parametrize("inertia, omega0", [([1.0, 2.0, 3.0], [3.0, 0.2, 1.0]),
                                             ([1.0, 5.0, 5.5], [30.0, 20.0, 10.0]),
                                             ([2.0, 1.0, 2.5], [0.0, 0.0, 1.2]),  # spins about
                                             ([2.0, 1.0, 2.5], [0.0, -0.7, 0.0])])  # stable axes
def test_exact_rates_reverse_mode_is_finite_over_long_times(inertia, omega0):
    # The closed form evaluates its principal-axis-spin branch for every body and discards it
    # by jnp.where; a branch that overflows there (a linearised flow growing like exp(mu t))
    # would turn the discarded cotangent into inf * 0 = NaN. Reverse mode against forward
    # mode, out to t = 2000. (The branch now gets the rates only at a spin, at rest otherwise;
    # before, the first two bodies gave NaN here, the second also with jax.scipy.linalg.expm.
    # At a stable spin, the flow's sinh, overflowing where its sin is used, did the same.)
    def f(w):
        return jnp.sum(jd.torque_free_omega(jnp.asarray(inertia), w, jnp.asarray([200.0, 2e3])))

    w0 = jnp.asarray(omega0)
    rev, fwd = np.asarray(jax.grad(f)(w0)), np.asarray(jax.jacfwd(f)(w0))
    assert np.all(np.isfinite(rev))
    np.testing.assert_allclose(rev, fwd, rtol=1e-9, atol=1e-12 * np.max(np.abs(fwd)))
    # float32 overflows sooner (sinh past 89): finite there too, at t = 200.
    def f32(w):
        return jnp.sum(jd.torque_free_omega(jnp.asarray(inertia, jnp.float32), w,
                                            jnp.asarray([200.0], jnp.float32)))

    assert np.all(np.isfinite(np.asarray(jax.grad(f32)(jnp.asarray(omega0, jnp.float32)))))
