"""Closed-form attitude of the torque-free body (`torque_free_attitude`), checked against an
independent tight integration of Euler's equations with the quaternion kinematics (scipy
DOP853, in numpy), conservation of the inertial angular momentum, the elementary closed forms
of the axisymmetric body and of a spin about a principal axis, and finite differences."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import FINITE_DIFF, INTEGRATION, ROUNDOFF, central_difference, tol, tree_allclose
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

import jaxdyn as jd

# The closed form against DOP853 at rtol=1e-13, atol=1e-14, over t <= 50 (several periods):
# the difference is the integrator's (it shrinks in proportion to its tolerance; about 1e-12
# at rtol=1e-12, below 4e-13 at rtol=3e-14).
AGAINST_DOP853 = 3e-12
# The same within 1e-6 of the separatrix, where the integration is less accurate: nearby
# orbits separate exponentially while they pass the intermediate axis.
NEAR_SEPARATRIX = tol(INTEGRATION)
# A fourth-order central difference in time, step 1e-3, against q' = q (x) (0, w) / 2.
KINEMATICS = 1e-10

TS = np.linspace(0.0, 50.0, 201)  # one shape for every comparison along a trajectory
Q0 = np.array([0.9, 0.1, -0.3, 0.2])  # not normalised on purpose


def _quat_multiply(p, q):
    p0, pv, q0, qv = p[..., :1], p[..., 1:], q[..., :1], q[..., 1:]
    return np.concatenate(
        [p0 * q0 - np.sum(pv * qv, -1, keepdims=True), p0 * qv + q0 * pv + np.cross(pv, qv)], -1
    )


def _integrate(inertia, omega0, quaternion0, ts):
    """Euler's equations and q' = q (x) (0, w) / 2 (7 states), by scipy's DOP853."""
    inertia = np.asarray(inertia, float)

    def rhs(_, y):
        w, q = y[:3], y[3:]
        w_dot = np.cross(inertia * w, w) / inertia
        return np.concatenate([w_dot, 0.5 * _quat_multiply(q, np.concatenate([[0.0], w]))])

    y0 = np.concatenate([omega0, quaternion0 / np.linalg.norm(quaternion0)])
    sol = solve_ivp(rhs, (0.0, ts[-1]), y0, method="DOP853", t_eval=ts, rtol=1e-13, atol=1e-14)
    assert sol.success
    return sol.y.T[:, 3:]


def _dcm(q):
    """[NB] of scalar-first quaternions, by scipy (scalar last)."""
    q = np.asarray(q, float)
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], -1)).as_matrix()


def _attitude(inertia, omega0, quaternion0=Q0, ts=TS):
    return np.asarray(jd.torque_free_attitude(inertia, omega0, quaternion0, ts))


def _side(inertia, omega):
    """Sign of H^2 - 2 T I_mid: +1 spinning about the major axis, -1 about the minor one."""
    mid = np.sort(inertia)[1]
    return np.sign(np.sum(inertia * (inertia - mid) * omega**2))


def _random_cases(per_side, seed):
    """Bodies (moments in any order, triangle inequality), rates on both sides of the
    separatrix with at least 2.5 periods of the rates in t <= 50, random attitudes."""
    rng = np.random.default_rng(seed)
    cases = {1.0: [], -1.0: []}
    while min(len(c) for c in cases.values()) < per_side:
        inertia = rng.uniform(0.5, 3.0, 3)
        omega0 = rng.normal(size=3)
        if inertia.max() > inertia.sum() - inertia.max():
            continue
        side = _side(inertia, omega0)
        period = float(jd.torque_free_period(inertia, omega0))
        if len(cases[side]) < per_side and period < TS[-1] / 2.5:
            cases[side].append((inertia, omega0, rng.normal(size=4)))
    return cases[1.0] + cases[-1.0]


CASES = _random_cases(3, seed=7) + [
    # |1 - n| > 4 (characteristic m / n instead), on each side; w1 = 0 (cn u0 = 0).
    (np.array([1.0, 1.75, 2.0]), np.array([0.2, 0.3, 1.0]), np.array([0.3, -0.2, 0.8, 0.1])),
    (np.array([2.0, 1.1, 1.0]), np.array([0.2, 0.6, 2.0]), np.array([0.5, 0.5, -0.5, 0.5])),
    (np.array([2.5, 1.0, 2.0]), np.array([1.0, 0.0, 0.5]), np.array([1.0, 0.0, 0.0, 0.0])),
]


@pytest.mark.parametrize("inertia, omega0, quaternion0", CASES)
def test_matches_tight_integration(inertia, omega0, quaternion0):
    q = _attitude(inertia, omega0, quaternion0)
    reference = _integrate(inertia, omega0, quaternion0, TS)
    assert np.max(np.abs(_dcm(q) - _dcm(reference))) < AGAINST_DOP853
    # q(0) is the given attitude, normalised, and q is continuous in t (no sign flips).
    np.testing.assert_allclose(q[0], quaternion0 / np.linalg.norm(quaternion0), atol=1e-15)
    assert np.max(np.linalg.norm(np.diff(q, axis=0), axis=-1)) < 0.5


def test_cases_cover_both_sides_and_several_periods():
    sides = [_side(inertia, omega0) for inertia, omega0, _ in CASES]
    assert sides.count(1.0) >= 3 and sides.count(-1.0) >= 3
    for inertia, omega0, _ in CASES:
        assert TS[-1] > 2.5 * float(jd.torque_free_period(inertia, omega0))


def _kinematics_residual(inertia, omega0, quaternion0):
    h = 1e-3
    q = [_attitude(inertia, omega0, quaternion0, TS + k * h) for k in (-2, -1, 1, 2)]
    q_dot = (q[0] - 8 * q[1] + 8 * q[2] - q[3]) / (12 * h)
    w = np.asarray(jd.torque_free_omega(inertia, omega0, TS))
    rhs = 0.5 * _quat_multiply(_attitude(inertia, omega0, quaternion0), np.insert(w, 0, 0.0, -1))
    return np.max(np.abs(q_dot - rhs))


def _separatrix_rates(inertia, w1, w2, relative):
    """Rates at a relative distance from the separatrix (I_mid is inertia[1])."""
    i1, i2, i3 = inertia
    w3 = w1 * np.sqrt(i1 * (i2 - i1) / (i3 * (i3 - i2))) * (1.0 + relative)
    return np.array([w1, w2, w3])


INVARIANT_CASES = CASES[:2] + [
    (np.array([1.0, 2.0, 2.5]), _separatrix_rates([1.0, 2.0, 2.5], 0.5, 0.3, 1e-6), Q0),
    (np.array([1.0, 2.0, 2.5]), _separatrix_rates([1.0, 2.0, 2.5], 0.5, 0.3, -1e-6), Q0),
]


@pytest.mark.parametrize("inertia, omega0, quaternion0", INVARIANT_CASES)
def test_invariants_and_kinematics(inertia, omega0, quaternion0):
    q = _attitude(inertia, omega0, quaternion0)
    w = np.asarray(jd.torque_free_omega(inertia, omega0, TS))
    h_n = np.einsum("tij,tj->ti", _dcm(q), inertia * w)
    assert np.max(np.linalg.norm(h_n - h_n[0], axis=-1)) < tol(ROUNDOFF) * np.linalg.norm(h_n[0])
    assert np.max(np.abs(np.linalg.norm(q, axis=-1) - 1.0)) < 1e-14
    # The angle about H (what the third-kind integral gives) is checked locally by the
    # kinematics q' = q (x) (0, w) / 2 with the rates of `torque_free_omega`.
    assert _kinematics_residual(inertia, omega0, quaternion0) < KINEMATICS


def _rotvec_matrix(axis, angle):
    return Rotation.from_rotvec(np.outer(angle, axis)).as_matrix()


@pytest.mark.parametrize(
    "inertia, omega0",
    [
        ([1.5, 1.0, 1.5], [0.3, -0.5, 0.8]),  # prolate, symmetry axis 2
        ([1.0, 2.0, 2.0], [0.7, 0.4, -0.2]),  # oblate, symmetry axis 1
        ([2.0, 2.0, 2.0], [0.3, 0.2, -0.1]),  # sphere
        ([1.0, 1.0, 1.8], [0.0, 0.0, 0.9]),  # spin about the symmetry axis
        ([1.0, 1.0, 1.8], [0.6, 0.0, 0.0]),  # spin about a transverse axis
    ],
)
def test_axisymmetric_elementary_closed_form(inertia, omega0):
    inertia, omega0 = np.asarray(inertia), np.asarray(omega0)
    i_t = np.sort(inertia)[1]
    axis = np.argmax(inertia != i_t) if np.any(inertia != i_t) else 0
    c0 = _dcm(Q0 / np.linalg.norm(Q0))
    h_n = c0 @ (inertia * omega0)
    big_h = np.linalg.norm(h_n)
    # [NB](t) = R(H_N, H t / I_t) [NB](0) R(e_a, (I_t - I_a) w_a t / I_t).
    precession = _rotvec_matrix(h_n / big_h if big_h else h_n, big_h * TS / i_t)
    relative = (i_t - inertia[axis]) * omega0[axis] / i_t
    spin = _rotvec_matrix(np.eye(3)[axis], relative * TS)
    expected = precession @ c0 @ spin
    q = _attitude(inertia, omega0)
    assert np.max(np.abs(_dcm(q) - expected)) < tol(ROUNDOFF)
    assert np.max(np.abs(_dcm(q) - _dcm(_integrate(inertia, omega0, Q0, TS)))) < AGAINST_DOP853


@pytest.mark.parametrize("relative", [1e-6, -1e-6, 0.0])
def test_near_and_on_the_separatrix(relative):
    inertia = np.array([1.0, 2.0, 2.5])
    omega0 = _separatrix_rates(inertia, 0.5, 0.3, relative)
    assert _side(inertia, omega0) == np.sign(relative) or relative == 0.0
    q = _attitude(inertia, omega0)
    assert np.max(np.abs(_dcm(q) - _dcm(_integrate(inertia, omega0, Q0, TS)))) < NEAR_SEPARATRIX
    # Finite and unit for long times (the period diverges as the separatrix is approached).
    late = _attitude(inertia, omega0, Q0, TS * 40.0)
    assert np.all(np.isfinite(late))
    assert np.max(np.abs(np.linalg.norm(late, axis=-1) - 1.0)) < 1e-13


def test_exactly_on_the_separatrix_tends_to_intermediate_axis_spin():
    inertia = np.array([1.0, 2.0, 3.0])
    omega0 = _separatrix_rates(inertia, 0.5, 0.3, 0.0)
    m, m1 = jd.elliptic_parameter(inertia, omega0)
    assert float(m1) == 0.0  # exactly: the elementary branch
    q = _attitude(inertia, omega0, Q0, TS * 40.0)
    assert np.all(np.isfinite(q))
    # Late on, a uniform rotation about H (along body axis 2) at the rate H / I_2.
    c = _dcm(q[-20:])
    h_n = _dcm(Q0 / np.linalg.norm(Q0)) @ (inertia * omega0)
    np.testing.assert_allclose(c[:, :, 1] * np.sign(omega0[1]), np.broadcast_to(
        h_n / np.linalg.norm(h_n), (20, 3)), atol=1e-9)
    dt = TS[1] * 40.0
    rotation = np.einsum("tji,tjk->tik", c[:-1], c[1:])  # [B_k B_k+1], about body axis 2
    angle = np.arctan2(-rotation[:, 2, 0], rotation[:, 0, 0])
    w2 = float(jd.torque_free_omega(inertia, omega0, TS[-1] * 40.0)[1])
    np.testing.assert_allclose(abs(w2), np.linalg.norm(h_n) / inertia[1], rtol=1e-12)
    np.testing.assert_allclose(np.exp(1j * angle), np.exp(1j * w2 * dt), atol=1e-9)


@pytest.mark.parametrize("omega0", [[0.0, 0.0, 1.2], [0.8, 0.0, 0.0], [0.0, -0.7, 0.0],
                                    [0.0, 0.0, 0.0]])
def test_spin_about_a_principal_axis(omega0):
    inertia = np.array([2.0, 1.0, 2.5])  # axis 1 is the intermediate one
    omega0 = np.asarray(omega0)
    c0 = _dcm(Q0 / np.linalg.norm(Q0))
    expected = c0 @ _rotvec_matrix(omega0, TS)
    q = _attitude(inertia, omega0)
    assert np.max(np.abs(_dcm(q) - expected)) < tol(ROUNDOFF)


def _objective(times):
    weights = jnp.asarray(np.arange(1.0, 13.0).reshape(3, 4))

    def f(x):
        return jnp.sum(jd.torque_free_attitude(x[:3], x[3:6], x[6:], times) * weights)

    return f


GRADIENT_POINTS = [
    ([2.5, 1.0, 2.0], [0.4, -0.3, 1.1]),  # generic, major-axis side, moments unsorted
    ([1.0, 2.4, 1.8], [1.2, 0.3, -0.4]),  # generic, minor-axis side
    ([2.5, 1.0, 2.0], [1.0, 0.0, 0.5]),  # cn u0 = 0 (a vanishing Carlson argument)
    ([2.0, 1.0, 2.5], [0.0, 0.0, 1.2]),  # spin about the major axis (H along it)
    ([2.0, 1.0, 2.5], [0.8, 0.0, 0.0]),  # spin about the intermediate axis
]


@pytest.mark.parametrize("inertia, omega0", GRADIENT_POINTS)
def test_gradients_match_finite_differences(inertia, omega0):
    x = np.concatenate([inertia, omega0, Q0])
    f = _objective(jnp.array([0.0, 3.7, 12.0]))
    grad = np.asarray(jax.jacfwd(f)(jnp.asarray(x)))
    fd = central_difference(f, x)
    assert np.all(np.isfinite(grad))
    scale = np.max(np.abs(fd))
    np.testing.assert_allclose(grad, fd, rtol=0, atol=tol(FINITE_DIFF) * scale)


def test_reverse_mode_is_finite_at_special_points():
    f = _objective(jnp.array([0.0, 3.7, 12.0]))
    grad = jax.jit(jax.grad(f))
    for inertia, omega0 in GRADIENT_POINTS + [([1.0, 2.0, 3.0], [0.5, 0.3, 0.5 / np.sqrt(3)]),
                                              ([1.0, 1.0, 1.5], [0.0, 0.0, 0.0])]:
        x = jnp.asarray(np.concatenate([inertia, omega0, Q0]))
        assert np.all(np.isfinite(grad(x)))


def test_float32_keeps_dtype():
    inertia, omega0, quaternion0 = CASES[0]
    q64 = _attitude(inertia, omega0, quaternion0)
    f32 = [jnp.asarray(v, jnp.float32) for v in (inertia, omega0, quaternion0, TS)]
    q32 = jd.torque_free_attitude(*f32)
    assert q32.dtype == jnp.float32
    early = TS <= 20.0  # (float32 round-off in the phase grows with t)
    assert np.max(np.abs(np.asarray(q32, np.float64) - q64)[early]) < tol(INTEGRATION, jnp.float32)
    assert np.all(np.isfinite(np.asarray(q32)))


def test_shapes():
    inertia, omega0, quaternion0 = CASES[0]
    for shape in [(), (5,), (2, 3)]:
        t = jax.ShapeDtypeStruct(shape, jnp.float64)
        out = jax.eval_shape(jd.torque_free_attitude, inertia, omega0, quaternion0, t)
        assert out.shape == shape + (4,) and out.dtype == jnp.float64


@pytest.mark.parametrize(
    "quaternion0, message",
    [
        ([0.0, 0.0, 0.0, 0.0], "quaternion0=[0., 0., 0., 0.]: must be nonzero"),
        ([1.0, float("nan"), 0.0, 0.0], "quaternion0=[ 1., nan,  0.,  0.]: must be finite"),
        ([1.0, 0.0, 0.0], "quaternion0 has shape (3,): expected shape (4,)"),
    ],
)
def test_bad_quaternion(quaternion0, message):
    with pytest.raises(jd.ParameterError, match=re.escape(message)):
        jd.torque_free_attitude([1.0, 2.0, 2.5], [0.1, 0.2, 0.3], quaternion0, 1.0)


@pytest.mark.parametrize("t", [None, "1.0", [0.5, None]])
def test_bad_times_name_the_field(t):
    # (`t=None` once fell through to a ValueError from unpacking, in both closed forms)
    for call in (lambda: jd.torque_free_attitude([1.0, 2.0, 2.5], [0.1, 0.2, 0.3], Q0, t),
                 lambda: jd.torque_free_omega([1.0, 2.0, 2.5], [0.1, 0.2, 0.3], t)):
        with pytest.raises(jd.ParameterError, match=r"^t="):
            call()


@pytest.mark.parametrize("inertia, omega0", [([2.0, 1.0, 2.5], [0.0, 0.0, 1.2]),
                                             ([2.0, 1.0, 2.5], [0.0, -0.7, 0.0]),
                                             ([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])])
def test_spin_and_rest_over_long_times(inertia, omega0):
    # A spin about a stable principal axis, and rest, out to t = 1e8: the rates stay put and
    # the attitude turns about the axis (scipy's rotation of the rotation vector w t). The
    # derivative branch (the linearised flow, zero in value) once made both NaN from about
    # t = 1e5 on (jax.scipy.linalg.expm's default of 16 squarings).
    ts = np.array([1e3, 3e5, 1e6, 1e8])
    omega0 = np.asarray(omega0)
    rates = np.asarray(jd.torque_free_omega(inertia, omega0, ts))
    np.testing.assert_array_equal(rates, np.broadcast_to(omega0, rates.shape))
    q = _attitude(inertia, omega0, Q0, ts)
    expected = _dcm(Q0 / np.linalg.norm(Q0)) @ _rotvec_matrix(omega0, ts)
    # (the angle w t carries the round-off of t's last bit: 1e8 * 1.2 * 2^-53 ~ 1e-8)
    assert np.max(np.abs(_dcm(q) - expected)) < 1e-7
    jac = np.asarray(jax.jacfwd(lambda w: jd.torque_free_attitude(inertia, w, Q0, ts[:3]))(
        jnp.asarray(omega0, float)))
    assert np.all(np.isfinite(jac))


def test_the_spin_branch_differentiates_as_the_linearised_flow_at_every_order():
    # At a spin about a principal axis the derivative with respect to the rates comes from
    # the linearised flow X(t) (lower left block of expm(A t), A = [[J, 0], [1, -skew(w)]])
    # times `omega - stop_gradient(omega)`, zero in value. The flow is now computed only where
    # a derivative is taken (a custom JVP rule): first and second derivatives, forward and
    # reverse, must be those of that product written out, and the mixed derivative by the
    # moments that of central differences of the first.
    from jaxdyn._free_body import euler_jacobian
    from jaxdyn._free_body_attitude import _spin_perturbation
    from jaxdyn._rotations import skew

    t = jnp.array([0.0, 0.8, 2.5])

    def product(inertia, omega):
        w_bar = jax.lax.stop_gradient(omega)
        a = jnp.block([[euler_jacobian(inertia, w_bar), jnp.zeros((3, 3))],
                       [jnp.eye(3), -skew(w_bar)]])
        flow = jax.vmap(lambda tt: jax.scipy.linalg.expm(a * tt))(t)[:, 3:, :3]
        return flow @ (omega - w_bar)

    weights = jnp.asarray(np.arange(1.0, 10.0).reshape(3, 3))

    def ours(i, w):
        return _spin_perturbation(i, w, t, jnp.asarray(True))

    def quadratic(fn):  # (a quadratic form: second derivatives that are not zero)
        return lambda i, w: jnp.sum(weights * fn(i, w) * (1.0 + fn(i, w)))

    orders = [
        lambda g: jax.jacfwd(g, argnums=1),
        lambda g: jax.jacfwd(jax.jacfwd(g, argnums=1), argnums=(0, 1)),
        lambda g: jax.jacfwd(jax.grad(g, argnums=1), argnums=(0, 1)),
        lambda g: jax.jacfwd(jax.grad(g, argnums=0), argnums=1),  # by the moments first
    ]
    # Every order in one program per side (compiled once: the expm's forward pass is shared).
    every = [jax.jit(lambda i, w, f=f: [o(quadratic(f))(i, w) for o in orders])
             for f in (ours, product)]
    first = jax.jit(jax.grad(quadratic(ours), argnums=1))
    for inertia, omega in [([2.0, 1.0, 2.5], [0.0, 0.0, 1.2]),  # major axis
                           ([2.0, 1.0, 2.5], [0.8, 0.0, 0.0])]:  # intermediate axis
        inertia, omega = jnp.asarray(inertia), jnp.asarray(omega)
        assert np.array_equal(ours(inertia, omega), np.zeros((3, 3)))
        for a, b in zip(*(fn(inertia, omega) for fn in every)):
            assert tree_allclose(a, b, rtol=1e-12, atol=1e-12)
        mixed = np.asarray(jax.jacfwd(first)(inertia, omega))
        fd = central_difference(lambda i: first(i, omega), inertia)
        assert np.max(np.abs(mixed)) > 1.0
        np.testing.assert_allclose(mixed, fd, rtol=0, atol=tol(FINITE_DIFF) * np.max(np.abs(fd)))
        # Where the branch is not taken, no flow is computed and the tangent is zero.
        _, tangent = jax.jvp(lambda w: _spin_perturbation(inertia, w, t, jnp.asarray(False)),
                             (omega,), (jnp.ones(3),))
        assert np.array_equal(tangent, np.zeros((3, 3)))
