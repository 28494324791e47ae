"""Tests for `jaxdyn._rotations`.

Reference values come from independent routes: `scipy.spatial.transform.Rotation` (whose
quaternions are scalar *last*), `scipy.linalg.expm` of skew matrices, NumPy cross products,
and central finite differences.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from helpers import FINITE_DIFF, INTEGRATION, ROUNDOFF, central_difference, tol
from scipy.spatial.transform import Rotation

import jaxdyn._rotations
from jaxdyn._rotations import (
    dcm_to_euler321,
    dcm_to_mrp,
    dcm_to_quat,
    euler321_to_dcm,
    euler321_to_quat,
    mrp_derivative,
    mrp_from_quat,
    mrp_shadow,
    mrp_switch,
    mrp_to_dcm,
    quat_conjugate,
    quat_derivative,
    quat_from_axis_angle,
    quat_from_mrp,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_to_axis_angle,
    quat_to_dcm,
    quat_to_euler321,
    safe_norm,
    skew,
)

# Time step of the central differences in t used to check the kinematics (error ~ h^2).
KINEMATICS_FD_STEP = 1e-5

N_SAMPLES = 300

# Fixed-step RK4 over T = 10 s; for |w| ~ 1 rad/s its error is ~1e-11, inside INTEGRATION.
RK4_DT = 1e-2
RK4_STEPS = 1000

# Jit once (per input shape), vectorised over the samples.
_quat_to_dcm = jax.jit(jax.vmap(quat_to_dcm))
_dcm_to_quat = jax.jit(jax.vmap(dcm_to_quat))
_quat_rotate = jax.jit(jax.vmap(quat_rotate))
_quat_multiply = jax.jit(jax.vmap(quat_multiply))
_quat_conjugate = jax.jit(jax.vmap(quat_conjugate))
_quat_normalize = jax.jit(jax.vmap(quat_normalize))
_quat_derivative = jax.jit(jax.vmap(quat_derivative))
_quat_from_axis_angle = jax.jit(jax.vmap(quat_from_axis_angle))
_quat_to_axis_angle = jax.jit(jax.vmap(quat_to_axis_angle))
_mrp_from_quat = jax.jit(jax.vmap(mrp_from_quat))
_quat_from_mrp = jax.jit(jax.vmap(quat_from_mrp))
_mrp_shadow = jax.jit(jax.vmap(mrp_shadow))
_mrp_switch = jax.jit(jax.vmap(mrp_switch))
_mrp_to_dcm = jax.jit(jax.vmap(mrp_to_dcm))
_dcm_to_mrp = jax.jit(jax.vmap(dcm_to_mrp))
_mrp_derivative = jax.jit(jax.vmap(mrp_derivative))
_euler321_to_dcm = jax.jit(jax.vmap(euler321_to_dcm))
_dcm_to_euler321 = jax.jit(jax.vmap(dcm_to_euler321))
_euler321_to_quat = jax.jit(jax.vmap(euler321_to_quat))
_quat_to_euler321 = jax.jit(jax.vmap(quat_to_euler321))
_skew = jax.jit(jax.vmap(skew))
_safe_norm = jax.jit(jax.vmap(safe_norm))


#
# Independent references and helpers
#


def _assert_close(actual, expected, rtol):
    """Compare O(1) quantities (unit quaternions, rotation matrices, angles) to `rtol`."""
    np.testing.assert_allclose(np.asarray(actual), np.asarray(expected), rtol=rtol, atol=rtol)


def _random_unit(rng, n, dim):
    x = rng.normal(size=(n, dim))
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _random_quats(rng, n=N_SAMPLES):
    """Random unit quaternions of both signs of q0, scalar first."""
    return _random_unit(rng, n, 4)


def _scipy_rotation(q):
    """SciPy rotation of scalar-first quaternions (SciPy is scalar last)."""
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])


def _scipy_quat(rotation):
    """Scalar-first quaternion of a SciPy rotation."""
    return rotation.as_quat()[..., [3, 0, 1, 2]]


def _np_skew(v):
    v1, v2, v3 = v
    return np.array([[0.0, -v3, v2], [v3, 0.0, -v1], [-v2, v1, 0.0]])


def _align_sign(q, reference):
    """Flip each quaternion of `q` to the sign of `reference` (q and -q are one attitude)."""
    q = np.asarray(q)
    sign = np.where(np.sum(q * reference, axis=-1, keepdims=True) < 0, -1.0, 1.0)
    return sign * q


def _shepperd_branch(C):
    """Index of the largest of 4 q_i^2 = (1 + tr C, 1 + 2 C_ii - tr C) / 4, from NumPy."""
    C = np.asarray(C)
    trace = np.trace(C, axis1=-2, axis2=-1)
    diag = np.diagonal(C, axis1=-2, axis2=-1)
    t = np.concatenate([(1.0 + trace)[..., None], 1.0 + 2.0 * diag - trace[..., None]], axis=-1)
    return np.argmax(t, axis=-1)


def _assert_grad_matches_fd(f, points):
    """`jax.grad(f)` against central differences at each point (one compilation in all)."""
    value_and_grad = jax.jit(jax.value_and_grad(f))
    for x0 in points:
        np.testing.assert_allclose(
            np.asarray(value_and_grad(x0)[1]),
            central_difference(lambda x: value_and_grad(x)[0], x0),
            rtol=tol(FINITE_DIFF),
            atol=tol(FINITE_DIFF),
        )
    return value_and_grad


def _rk4(vector_field, y0, dt, num_steps, post_step=lambda y: y):
    """Classical fixed-step RK4; `post_step` is applied after each step. Returns all states."""

    def step(y, _):
        k1 = vector_field(y)
        k2 = vector_field(y + 0.5 * dt * k1)
        k3 = vector_field(y + 0.5 * dt * k2)
        k4 = vector_field(y + dt * k3)
        y = post_step(y + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4))
        return y, y

    _, ys = jax.lax.scan(step, y0, None, length=num_steps)
    return jnp.concatenate([y0[None], ys], axis=0)


@jax.jit
def _integrate_mrp(sigma0, w):
    """MRP kinematics at constant body rate, switching to the shadow set after each step."""
    return _rk4(lambda s: mrp_derivative(s, w), sigma0, RK4_DT, RK4_STEPS, mrp_switch)


@jax.jit
def _integrate_quat(q0, w):
    return _rk4(lambda q: quat_derivative(q, w), q0, RK4_DT, RK4_STEPS)


#
# Generic helpers
#


def test_skew_matches_cross():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(N_SAMPLES, 3))
    u = rng.normal(size=(N_SAMPLES, 3))
    S = np.asarray(_skew(v))
    _assert_close(np.einsum("nij,nj->ni", S, u), np.cross(v, u), tol(ROUNDOFF))
    _assert_close(S, -np.swapaxes(S, -1, -2), tol(ROUNDOFF))


def test_safe_norm_value_and_gradient():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(N_SAMPLES, 5))
    _assert_close(_safe_norm(x), np.linalg.norm(x, axis=-1), tol(ROUNDOFF))
    # Other axes / keepdims.
    norm = jax.jit(safe_norm, static_argnames=("axis", "keepdims"))
    _assert_close(norm(x, axis=0), np.linalg.norm(x, axis=0), tol(ROUNDOFF))
    assert jax.eval_shape(lambda y: safe_norm(y, keepdims=True), x).shape == (N_SAMPLES, 1)
    # Gradient: x / |x| away from zero, exactly 0 (not NaN) at zero.
    grads = jax.jit(jax.vmap(jax.grad(safe_norm)))(x)
    _assert_close(grads, x / np.linalg.norm(x, axis=-1, keepdims=True), tol(ROUNDOFF))
    grad0 = jax.jit(jax.grad(safe_norm))(jnp.zeros(3))
    np.testing.assert_array_equal(np.asarray(grad0), np.zeros(3))
    assert float(norm(np.zeros(3))) == 0.0


def test_a_concrete_vector_is_normalised_on_the_host_as_unit_does_it():
    """`_validation.nonzero_unit` (the checks that normalise a given quaternion or axis)
    normalises a concrete vector by NumPy on the host, where `unit`'s eager operations
    compiled a dozen programs: the same vector to a unit in the last place (float64 and
    float32, integers, components near overflow and underflow, rows), the same dtype."""
    from jaxdyn._rotations import unit
    from jaxdyn._validation import ParameterError, nonzero_unit

    rng = np.random.default_rng(8)
    cases = [rng.normal(size=4), rng.normal(size=(6, 3)), np.array([1e300, -2e300, 2e300]),
             np.array([3e-300, 4e-300, 0.0]), np.array([1, 2, 2]),
             rng.normal(size=3).astype(np.float32), [0.0, 0.6, 0.8]]
    for x in cases:
        got, want = nonzero_unit("v", x), unit(jnp.asarray(x))
        assert isinstance(got, jax.Array) and got.dtype == want.dtype
        eps = np.finfo(want.dtype).eps
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=2 * eps, atol=0)
        np.testing.assert_allclose(np.linalg.norm(np.asarray(got, float), axis=-1), 1.0,
                                   rtol=4 * eps)
    with pytest.raises(ParameterError, match="must be nonzero"):
        nonzero_unit("v", [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


#
# Quaternions
#


def test_quat_to_dcm_orthonormal_and_matches_scipy():
    rng = np.random.default_rng(2)
    q = _random_quats(rng)
    C = np.asarray(_quat_to_dcm(q))
    eye = np.broadcast_to(np.eye(3), C.shape)
    _assert_close(C @ np.swapaxes(C, -1, -2), eye, tol(ROUNDOFF))
    _assert_close(np.linalg.det(C), np.ones(N_SAMPLES), tol(ROUNDOFF))
    _assert_close(C, _scipy_rotation(q).as_matrix(), tol(ROUNDOFF))
    # q and -q give the same matrix.
    _assert_close(_quat_to_dcm(-q), C, tol(ROUNDOFF))


def test_quat_rotate_matches_scipy():
    rng = np.random.default_rng(3)
    q = _random_quats(rng)
    v = rng.normal(size=(N_SAMPLES, 3))
    expected = _scipy_rotation(q).apply(v)
    _assert_close(_quat_rotate(q, v), expected, tol(ROUNDOFF))
    # v_N = [NB] v_B
    _assert_close(np.einsum("nij,nj->ni", _quat_to_dcm(q), v), expected, tol(ROUNDOFF))
    # Broadcasting one quaternion against many vectors, without vmap.
    _assert_close(jax.jit(quat_rotate)(q[0], v), _scipy_rotation(q[0]).apply(v), tol(ROUNDOFF))


def test_quat_multiply_and_conjugate_match_scipy():
    rng = np.random.default_rng(4)
    p = _random_quats(rng)
    q = _random_quats(rng)
    pq = np.asarray(_quat_multiply(p, q))
    expected = _scipy_rotation(p) * _scipy_rotation(q)  # matrix R(p) @ R(q)
    _assert_close(pq, _align_sign(_scipy_quat(expected), pq), tol(ROUNDOFF))
    _assert_close(_quat_to_dcm(pq), expected.as_matrix(), tol(ROUNDOFF))
    # Hamilton product by hand for the basis: i j = k.
    i, j, k = np.eye(4)[1], np.eye(4)[2], np.eye(4)[3]
    _assert_close(_quat_multiply(i[None], j[None])[0], k, tol(ROUNDOFF))
    # Conjugate is the inverse.
    q_conj = np.asarray(_quat_conjugate(q))
    _assert_close(q_conj, q * np.array([1.0, -1.0, -1.0, -1.0]), 0.0)
    _assert_close(_quat_to_dcm(q_conj), _scipy_rotation(q).inv().as_matrix(), tol(ROUNDOFF))


def test_quat_normalize():
    rng = np.random.default_rng(5)
    x = rng.normal(size=(N_SAMPLES, 4)) * rng.uniform(1e-3, 1e3, size=(N_SAMPLES, 1))
    q = np.asarray(_quat_normalize(x))
    _assert_close(np.linalg.norm(q, axis=-1), np.ones(N_SAMPLES), tol(ROUNDOFF))
    _assert_close(q, x / np.linalg.norm(x, axis=-1, keepdims=True), tol(ROUNDOFF))
    # Gradient against central differences, at a non-unit quaternion.
    w = rng.normal(size=4)

    def f(y):
        return jnp.sum(w * quat_normalize(y))

    value_and_grad = _assert_grad_matches_fd(f, [rng.normal(size=4) * 3.0])
    # Tiny but nonzero quaternion: still finite.
    assert np.all(np.isfinite(np.asarray(value_and_grad(np.array([1e-30, 0.0, 0.0, 0.0]))[1])))


def test_dcm_to_quat_round_trip():
    rng = np.random.default_rng(6)
    q = _random_quats(rng)
    C = _scipy_rotation(q).as_matrix()
    q_back = np.asarray(_dcm_to_quat(C))
    assert np.all(q_back[:, 0] >= 0)
    _assert_close(q_back, np.where(q[:, :1] < 0, -q, q), tol(ROUNDOFF))
    _assert_close(_dcm_to_quat(_quat_to_dcm(q)), np.where(q[:, :1] < 0, -q, q), tol(ROUNDOFF))


def _shepperd_cases(rng, n_per_branch=50):
    """Rotation matrices (from SciPy) grouped by which Shepperd branch must be selected."""
    cases = {}
    # Branch 0 (q0 largest): rotations by less than 90 degrees, some extremely small.
    axes = _random_unit(rng, n_per_branch, 3)
    angles = rng.uniform(0.0, np.pi / 2, size=n_per_branch)
    angles[:5] = [0.0, 1e-12, 1e-8, 1e-4, 1e-2]
    cases[0] = Rotation.from_rotvec(axes * angles[:, None])
    # Branch i (q_i largest): rotations by (almost) 180 degrees about an axis close to e_i.
    for i in range(3):
        axes = np.eye(3)[i] + 0.15 * rng.normal(size=(n_per_branch, 3))
        axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
        axes[0] = np.eye(3)[i]  # exactly 180 degrees about e_i: C = 2 e_i e_iᵀ - I
        angles = np.pi - rng.uniform(0.0, 0.3, size=n_per_branch)
        angles[:4] = [np.pi, np.pi, np.pi - 1e-12, np.pi - 1e-6]
        angles *= rng.choice([-1.0, 1.0], size=n_per_branch)
        cases[i + 1] = Rotation.from_rotvec(axes * angles[:, None])
    return cases


def test_dcm_to_quat_every_shepperd_branch():
    rng = np.random.default_rng(7)
    for branch, rotation in _shepperd_cases(rng).items():
        C = rotation.as_matrix()
        np.testing.assert_array_equal(_shepperd_branch(C), branch)
        q = np.asarray(_dcm_to_quat(C))
        assert np.all(q[:, 0] >= 0), branch
        expected = _scipy_quat(rotation)
        _assert_close(q, _align_sign(expected, q), tol(ROUNDOFF))
        _assert_close(_quat_to_dcm(q), C, tol(ROUNDOFF))


def test_dcm_to_quat_gradient_finite():
    rng = np.random.default_rng(8)
    half_turns = [
        np.diag([1.0, -1.0, -1.0]),
        np.diag([-1.0, 1.0, -1.0]),
        np.diag([-1.0, -1.0, 1.0]),
        Rotation.from_rotvec(np.pi * np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)).as_matrix(),
        Rotation.from_rotvec(np.pi * _random_unit(rng, 1, 3)[0]).as_matrix(),
        Rotation.from_rotvec((np.pi - 1e-9) * _random_unit(rng, 1, 3)[0]).as_matrix(),
    ]
    jac = jax.jit(jax.jacobian(dcm_to_quat))
    for C in [np.eye(3), *half_turns]:
        assert np.all(np.isfinite(np.asarray(jac(C))))

    # Identity: compare with central differences (branch 0 is selected in a neighbourhood).
    weights = rng.normal(size=4)

    def f(x):
        return jnp.sum(weights * dcm_to_quat(x.reshape(3, 3)))

    _assert_grad_matches_fd(f, [np.eye(3).reshape(-1)])
    # 180 degrees: q0 = 0 so the sign of q flips under perturbation; q qᵀ is sign-free.
    weights44 = rng.normal(size=(4, 4))

    def g(x):
        q = dcm_to_quat(x.reshape(3, 3))
        return jnp.sum(weights44 * q[:, None] * q[None, :])

    _assert_grad_matches_fd(g, [C.reshape(-1) for C in half_turns])


def test_quat_axis_angle_matches_scipy():
    rng = np.random.default_rng(9)
    axes = rng.normal(size=(N_SAMPLES, 3))  # not unit: normalised internally
    unit_axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    angles = rng.uniform(-2.0 * np.pi, 2.0 * np.pi, size=N_SAMPLES)
    q = np.asarray(_quat_from_axis_angle(axes, angles))
    expected = _scipy_quat(Rotation.from_rotvec(unit_axes * angles[:, None]))
    _assert_close(q, _align_sign(expected, q), tol(ROUNDOFF))
    _assert_close(_quat_to_dcm(q)[0], scipy.linalg.expm(angles[0] * _np_skew(unit_axes[0])), 1e-12)

    q = _random_quats(rng)
    axis, angle = _quat_to_axis_angle(q)
    angle = np.asarray(angle)
    assert np.all((angle >= 0) & (angle <= np.pi))
    _assert_close(np.linalg.norm(axis, axis=-1), np.ones(N_SAMPLES), tol(ROUNDOFF))
    _assert_close(np.asarray(axis) * angle[:, None], _scipy_rotation(q).as_rotvec(), 1e-12)


def test_quat_axis_angle_gradients_at_identity():
    @jax.jit
    def derivatives(axis, q):
        dq_daxis, dq_dangle = jax.jacobian(quat_from_axis_angle, argnums=(0, 1))(axis, 0.0)
        # The rotation angle as a function of the angle, differentiated through 0.
        round_trip = jax.grad(lambda a: quat_to_axis_angle(quat_from_axis_angle(axis, a))[1])
        return (
            dq_daxis,
            dq_dangle,
            quat_to_axis_angle(q),
            jax.jacobian(quat_to_axis_angle)(q),
            round_trip(0.0),
        )

    axis = np.array([0.3, -0.4, 1.2])
    for q in [np.array([1.0, 0.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0, 0.0])]:
        dq_daxis, dq_dangle, (axis_out, angle_out), jacobians, round_trip = derivatives(axis, q)
        # d/dangle at angle 0 is (0, axis / (2 |axis|)); d/daxis is 0.
        expected = np.concatenate([[0.0], 0.5 * axis / np.linalg.norm(axis)])
        _assert_close(dq_dangle, expected, 1e-14)
        np.testing.assert_array_equal(np.asarray(dq_daxis), np.zeros((4, 3)))
        # At the identity: angle 0, some unit axis, finite Jacobians.
        assert float(angle_out) == 0.0
        _assert_close(np.linalg.norm(axis_out), 1.0, tol(ROUNDOFF))
        for jac in jacobians:
            assert np.all(np.isfinite(np.asarray(jac)))
        assert np.isfinite(float(round_trip))


#
# Modified Rodrigues parameters
#


def test_mrp_from_quat_matches_scipy():
    rng = np.random.default_rng(10)
    q = _random_quats(rng)
    sigma = np.asarray(_mrp_from_quat(q))
    assert np.all(np.linalg.norm(sigma, axis=-1) <= 1.0 + tol(ROUNDOFF))
    _assert_close(sigma, _scipy_rotation(q).as_mrp(), tol(ROUNDOFF))
    # Same attitude for q and -q.
    _assert_close(_mrp_from_quat(-q), sigma, tol(ROUNDOFF))


def test_mrp_to_dcm_matches_scipy():
    rng = np.random.default_rng(11)
    sigma = _random_unit(rng, N_SAMPLES, 3) * rng.uniform(0.0, 3.0, size=(N_SAMPLES, 1))
    expected = Rotation.from_mrp(sigma).as_matrix()
    _assert_close(_mrp_to_dcm(sigma), expected, tol(ROUNDOFF))
    _assert_close(_quat_to_dcm(_quat_from_mrp(sigma)), expected, tol(ROUNDOFF))


def test_mrp_round_trips():
    rng = np.random.default_rng(12)
    q = _random_quats(rng)
    q_pos = np.where(q[:, :1] < 0, -q, q)
    # quat -> mrp -> quat gives the q0 >= 0 representative.
    _assert_close(_quat_from_mrp(_mrp_from_quat(q)), q_pos, tol(ROUNDOFF))
    # dcm -> mrp -> dcm, and mrp of a dcm equals SciPy's (|sigma| <= 1) set.
    C = _scipy_rotation(q).as_matrix()
    sigma = np.asarray(_dcm_to_mrp(C))
    _assert_close(sigma, _scipy_rotation(q).as_mrp(), tol(ROUNDOFF))
    _assert_close(_mrp_to_dcm(sigma), C, tol(ROUNDOFF))
    # mrp -> quat -> mrp for |sigma| <= 1, and for |sigma| > 1 it returns the shadow set.
    sigma = _random_unit(rng, N_SAMPLES, 3) * rng.uniform(0.0, 3.0, size=(N_SAMPLES, 1))
    inside = np.linalg.norm(sigma, axis=-1, keepdims=True) <= 1.0
    expected = np.where(inside, sigma, -sigma / np.sum(sigma**2, axis=-1, keepdims=True))
    _assert_close(_mrp_from_quat(_quat_from_mrp(sigma)), expected, tol(ROUNDOFF))
    _assert_close(_dcm_to_mrp(Rotation.from_mrp(sigma).as_matrix()), expected, tol(ROUNDOFF))


def test_mrp_shadow_and_switch():
    rng = np.random.default_rng(13)
    sigma = _random_unit(rng, N_SAMPLES, 3) * rng.uniform(0.05, 3.0, size=(N_SAMPLES, 1))
    norms = np.linalg.norm(sigma, axis=-1)
    shadow = np.array(_mrp_shadow(sigma))  # writable copy, for SciPy
    _assert_close(np.linalg.norm(shadow, axis=-1) * norms, np.ones(N_SAMPLES), tol(ROUNDOFF))
    _assert_close(Rotation.from_mrp(shadow).as_matrix(), _mrp_to_dcm(sigma), tol(ROUNDOFF))
    _assert_close(_mrp_to_dcm(shadow), Rotation.from_mrp(sigma).as_matrix(), tol(ROUNDOFF))
    _assert_close(_mrp_shadow(shadow), sigma, tol(ROUNDOFF))

    switched = np.asarray(_mrp_switch(sigma))
    assert np.all(np.linalg.norm(switched, axis=-1) <= 1.0 + tol(ROUNDOFF))
    inside = norms <= 1.0
    np.testing.assert_array_equal(switched[inside], sigma[inside])
    _assert_close(switched[~inside], shadow[~inside], tol(ROUNDOFF))
    _assert_close(_mrp_to_dcm(switched), Rotation.from_mrp(sigma).as_matrix(), tol(ROUNDOFF))

    # Gradients: identity at 0 (no NaN from the unselected branch), d(shadow) outside.
    jac0 = jax.jit(jax.jacobian(mrp_switch))(jnp.zeros(3))
    np.testing.assert_array_equal(np.asarray(jac0), np.eye(3))
    weights = rng.normal(size=3)

    def f(s):
        return jnp.sum(weights * mrp_switch(s))

    _assert_grad_matches_fd(f, [sigma[~inside][0], sigma[inside][0]])


def test_mrp_derivative_matches_finite_difference():
    """sigma(t) of [NB](t) = [NB](0) expm(t [w×]) from SciPy, differenced in t."""
    rng = np.random.default_rng(14)
    n = N_SAMPLES
    C0 = Rotation.random(n, random_state=rng).as_matrix()
    w = rng.normal(size=(n, 3))
    t0 = rng.uniform(0.0, 3.0, size=n)
    h = KINEMATICS_FD_STEP

    def attitude(t):  # exp(t [w×]) via SciPy's rotation vectors (vectorised)
        return Rotation.from_matrix(C0 @ Rotation.from_rotvec(t[:, None] * w).as_matrix())

    sigma_minus, sigma, sigma_plus = (attitude(t0 + d).as_mrp() for d in (-h, 0.0, h))
    # Stay away from |sigma| = 1, where SciPy's canonical set switches within [t - h, t + h].
    keep = np.linalg.norm(sigma, axis=-1) < 0.95
    assert keep.sum() > n // 2
    fd = (sigma_plus - sigma_minus) / (2.0 * h)
    np.testing.assert_allclose(
        np.asarray(_mrp_derivative(sigma, w))[keep],
        fd[keep],
        rtol=tol(FINITE_DIFF),
        atol=tol(FINITE_DIFF),
    )

    # The same kinematics hold for the shadow set.
    def shadow(s):
        return -s / np.sum(s**2, axis=-1, keepdims=True)

    # (Away from sigma = 0, where the shadow set is at infinity.)
    keep &= np.linalg.norm(sigma, axis=-1) > 0.3
    fd_shadow = (shadow(sigma_plus) - shadow(sigma_minus)) / (2.0 * h)
    np.testing.assert_allclose(
        np.asarray(_mrp_derivative(shadow(sigma), w))[keep],
        fd_shadow[keep],
        rtol=tol(FINITE_DIFF),
        atol=tol(FINITE_DIFF),
    )


@pytest.mark.parametrize("generic_start", [False, True])
def test_mrp_integration_with_switching(generic_start):
    """RK4 on sigma_dot with switching, constant w, for about two revolutions.

    The closed form is [NB](t) = [NB](0) expm(t [w×]). Starting from a rotation about the
    spin axis itself, the rotation angle sweeps through 180 degrees (twice), so the switch
    to the shadow set must happen.
    """
    rng = np.random.default_rng(15)
    axis = _random_unit(rng, 1, 3)[0]
    rate = 1.3
    w = rate * axis
    if generic_start:
        C0 = Rotation.random(random_state=rng).as_matrix()
    else:
        C0 = scipy.linalg.expm(2.0 * _np_skew(axis))
    sigmas = np.asarray(_integrate_mrp(Rotation.from_matrix(C0).as_mrp(), w))
    assert np.all(np.linalg.norm(sigmas, axis=-1) <= 1.0 + tol(ROUNDOFF))
    jumps = np.linalg.norm(np.diff(sigmas, axis=0), axis=-1) > 0.5
    if not generic_start:
        assert jumps.sum() >= 2

    dcms = np.asarray(_mrp_to_dcm(sigmas))
    times = RK4_DT * np.arange(RK4_STEPS + 1)
    every = slice(None, None, 10)  # expm at 101 of the 1001 times
    expected = np.stack([C0 @ scipy.linalg.expm(t * _np_skew(w)) for t in times[every]])
    np.testing.assert_allclose(dcms[every], expected, rtol=tol(INTEGRATION), atol=tol(INTEGRATION))
    # The attitude is continuous through the switches: each step moves it by ~ |w| dt.
    steps = np.linalg.norm(np.diff(dcms, axis=0), axis=(-2, -1))
    assert steps.max() <= 2.0 * rate * RK4_DT


#
# Quaternion kinematics
#


def test_quat_derivative_matches_finite_difference():
    """q(t) = q_init ⊗ quat_from_axis_angle(axis, rate t) has body rate w = rate axis."""
    rng = np.random.default_rng(16)
    q_init = _random_quats(rng)
    axes = _random_unit(rng, N_SAMPLES, 3)
    rates = rng.uniform(-3.0, 3.0, size=N_SAMPLES)
    t0 = rng.uniform(0.0, 5.0, size=N_SAMPLES)
    h = KINEMATICS_FD_STEP

    def q_of_t(t):
        return np.asarray(_quat_multiply(q_init, _quat_from_axis_angle(axes, rates * t)))

    fd = (q_of_t(t0 + h) - q_of_t(t0 - h)) / (2.0 * h)
    w = rates[:, None] * axes
    np.testing.assert_allclose(
        np.asarray(_quat_derivative(q_of_t(t0), w)),
        fd,
        rtol=tol(FINITE_DIFF),
        atol=tol(FINITE_DIFF),
    )
    # Equivalent matrix form: d[NB]/dt = [NB] [w×].
    C = np.asarray(_quat_to_dcm(q_of_t(t0)))
    dq = np.asarray(_quat_derivative(q_of_t(t0), w))
    dC = jax.jit(jax.vmap(lambda x, dx: jax.jvp(quat_to_dcm, (x,), (dx,))[1]))(q_of_t(t0), dq)
    skews = np.stack([_np_skew(v) for v in w])
    _assert_close(dC, C @ skews, 1e-12)


def test_quat_derivative_integration():
    rng = np.random.default_rng(17)
    q0 = _random_quats(rng, 1)[0]
    axis = _random_unit(rng, 1, 3)[0]
    rate = -1.1
    w = rate * axis
    qs = np.asarray(_integrate_quat(q0, w))
    times = RK4_DT * np.arange(RK4_STEPS + 1)
    expected = _scipy_quat(_scipy_rotation(q0) * Rotation.from_rotvec(times[:, None] * w))
    np.testing.assert_allclose(
        qs, _align_sign(expected, qs), rtol=tol(INTEGRATION), atol=tol(INTEGRATION)
    )
    C0 = _scipy_rotation(q0).as_matrix()
    every = slice(None, None, 10)  # expm at 101 of the 1001 times
    closed_form = np.stack([C0 @ scipy.linalg.expm(t * _np_skew(w)) for t in times[every]])
    np.testing.assert_allclose(
        _scipy_rotation(qs[every]).as_matrix(),
        closed_form,
        rtol=tol(INTEGRATION),
        atol=tol(INTEGRATION),
    )


#
# 3-2-1 Euler angles
#


def _random_euler(rng, n=N_SAMPLES, max_pitch=np.pi / 2):
    psi = rng.uniform(-np.pi, np.pi, size=n)
    theta = rng.uniform(-max_pitch, max_pitch, size=n)
    phi = rng.uniform(-np.pi, np.pi, size=n)
    return np.stack([psi, theta, phi], axis=-1)


def test_euler321_matches_scipy():
    rng = np.random.default_rng(18)
    angles = _random_euler(rng)
    rotation = Rotation.from_euler("ZYX", angles)  # intrinsic: R3(psi) R2(theta) R1(phi)
    _assert_close(_euler321_to_dcm(angles), rotation.as_matrix(), tol(ROUNDOFF))
    q = np.asarray(_euler321_to_quat(angles))
    _assert_close(q, _align_sign(_scipy_quat(rotation), q), tol(ROUNDOFF))
    # Elementary rotations are active, right-handed: R3(psi) e1 = (cos psi, sin psi, 0).
    C = np.asarray(_euler321_to_dcm(np.array([[0.3, 0.0, 0.0]])))[0]
    _assert_close(C[:, 0], [np.cos(0.3), np.sin(0.3), 0.0], tol(ROUNDOFF))
    # ... and are applied in the order yaw, then pitch about the new 2-axis, then roll.
    psi, theta, phi = angles[0]
    by_hand = (
        scipy.linalg.expm(psi * _np_skew([0.0, 0.0, 1.0]))
        @ scipy.linalg.expm(theta * _np_skew([0.0, 1.0, 0.0]))
        @ scipy.linalg.expm(phi * _np_skew([1.0, 0.0, 0.0]))
    )
    _assert_close(_euler321_to_dcm(angles)[0], by_hand, 1e-12)


def test_euler321_round_trip():
    rng = np.random.default_rng(19)
    angles = _random_euler(rng, max_pitch=np.pi / 2 - 0.05)
    _assert_close(_dcm_to_euler321(_euler321_to_dcm(angles)), angles, tol(ROUNDOFF))
    _assert_close(_quat_to_euler321(_euler321_to_quat(angles)), angles, tol(ROUNDOFF))
    # Arbitrary rotations: agree with SciPy's extraction.
    q = _random_quats(rng)
    rotation = _scipy_rotation(q)
    _assert_close(_dcm_to_euler321(rotation.as_matrix()), rotation.as_euler("ZYX"), 1e-10)
    _assert_close(_quat_to_euler321(q), rotation.as_euler("ZYX"), 1e-10)
    # Close to gimbal lock the angles are ill-conditioned, but they still reproduce the dcm.
    near = _random_euler(rng, n=50)
    near[:, 1] = rng.choice([-1.0, 1.0], size=50) * (np.pi / 2 - 10.0 ** rng.uniform(-15, -3, 50))
    C = Rotation.from_euler("ZYX", near).as_matrix()
    _assert_close(_euler321_to_dcm(_dcm_to_euler321(C)), C, tol(ROUNDOFF))


@jax.jit
@jax.vmap
def _euler_derivatives(angles, C):
    """Derivatives of the Euler-angle extraction, directly and through the composite maps."""
    return (
        jax.jacobian(dcm_to_euler321)(C),
        jax.grad(lambda x: jnp.sum(dcm_to_euler321(euler321_to_dcm(x))))(angles),
        jax.grad(lambda x: jnp.sum(quat_to_euler321(euler321_to_quat(x))))(angles),
    )


@pytest.mark.parametrize("pitch", [np.pi / 2, -np.pi / 2])
def test_euler321_gimbal_lock(pitch):
    rng = np.random.default_rng(20)
    angles = _random_euler(rng)
    angles[:, 1] = pitch
    matrices = [
        Rotation.from_euler("ZYX", angles).as_matrix(),
        np.asarray(_euler321_to_dcm(angles)),
        np.asarray(_quat_to_dcm(_euler321_to_quat(angles))),
    ]
    # Exact gimbal-lock matrices (entries exactly 0 and ±1): C = R3(a) R2(pitch).
    a = rng.uniform(-np.pi, np.pi, size=N_SAMPLES)
    ca, sa, sp = np.cos(a), np.sin(a), np.sign(pitch)
    zero = np.zeros(N_SAMPLES)
    exact = np.stack(
        [
            np.stack([zero, -sa, sp * ca], axis=-1),
            np.stack([zero, ca, sp * sa], axis=-1),
            np.stack([-sp * np.ones(N_SAMPLES), zero, zero], axis=-1),
        ],
        axis=-2,
    )
    matrices.append(exact)
    for C in matrices:
        out = np.asarray(_dcm_to_euler321(C))
        assert np.all(np.isfinite(out))
        _assert_close(out[:, 1], np.full(N_SAMPLES, pitch), tol(ROUNDOFF))
        _assert_close(_euler321_to_dcm(out), C, tol(ROUNDOFF))
        for derivative in _euler_derivatives(angles, C):
            assert np.all(np.isfinite(np.asarray(derivative)))
    # Only phi - psi (pitch +90) or phi + psi (pitch -90) is determined.
    out = np.asarray(_dcm_to_euler321(matrices[0]))
    combo = angles[:, 2] - np.sign(pitch) * angles[:, 0]
    out_combo = out[:, 2] - np.sign(pitch) * out[:, 0]
    _assert_close(np.exp(1j * out_combo), np.exp(1j * combo), 1e-10)
    # Quaternion route, and gradients through the composite maps.
    q = _euler321_to_quat(angles)
    out_q = np.asarray(_quat_to_euler321(q))
    assert np.all(np.isfinite(out_q))
    _assert_close(_euler321_to_dcm(out_q), matrices[0], tol(ROUNDOFF))


def test_gradients_match_finite_differences():
    """Gradients of the conversions that select branches, at a generic attitude."""
    rng = np.random.default_rng(24)
    x0 = np.array([0.8, 0.3, -0.5, 0.4])  # not unit; q0 > 0, pitch well inside +-90 deg
    weights = rng.normal(size=(2, 4))

    def f(x):
        q = quat_normalize(x)
        axis, angle = quat_to_axis_angle(q)
        terms = [jnp.append(axis, angle), jnp.append(dcm_to_euler321(quat_to_dcm(q)), 0.0)]
        return jnp.sum(weights * jnp.stack(terms))

    _assert_grad_matches_fd(f, [x0, -x0])


#
# dtypes and batching
#


def _all_calls(dtype):
    """(name, function, float64 vmapped reference, args) for every public function.

    The inputs have `dtype`; the shapes match those used above, so that the jitted
    references are usually already compiled.
    """
    rng = np.random.default_rng(21)
    rotation = Rotation.from_euler("ZYX", _random_euler(rng, max_pitch=1.3))
    angles = rotation.as_euler("ZYX")
    C = rotation.as_matrix()
    q = _scipy_quat(rotation) * rng.choice([-1.0, 1.0], size=(N_SAMPLES, 1))
    v = rng.normal(size=(N_SAMPLES, 3))
    sigma = _random_unit(rng, N_SAMPLES, 3) * rng.uniform(0.3, 2.0, size=(N_SAMPLES, 1))
    angle = rng.uniform(-3.0, 3.0, size=N_SAMPLES)
    q, v, sigma, C, angles, angle = (
        np.asarray(x, dtype=dtype) for x in (q, v, sigma, C, angles, angle)
    )
    half = np.full(N_SAMPLES, 0.5)
    return [
        ("quat_multiply", quat_multiply, _quat_multiply, (q, q[::-1])),
        ("quat_conjugate", quat_conjugate, _quat_conjugate, (q,)),
        ("quat_normalize", quat_normalize, _quat_normalize, (2.0 * q,)),
        ("quat_to_dcm", quat_to_dcm, _quat_to_dcm, (q,)),
        ("dcm_to_quat", dcm_to_quat, _dcm_to_quat, (C,)),
        ("quat_rotate", quat_rotate, _quat_rotate, (q, v)),
        ("quat_derivative", quat_derivative, _quat_derivative, (q, v)),
        ("quat_from_axis_angle", quat_from_axis_angle, _quat_from_axis_angle, (v, angle)),
        ("quat_to_axis_angle", quat_to_axis_angle, _quat_to_axis_angle, (q,)),
        ("mrp_from_quat", mrp_from_quat, _mrp_from_quat, (q,)),
        ("quat_from_mrp", quat_from_mrp, _quat_from_mrp, (sigma,)),
        ("mrp_shadow", mrp_shadow, _mrp_shadow, (sigma,)),
        ("mrp_switch", mrp_switch, _mrp_switch, (sigma,)),
        ("mrp_to_dcm", mrp_to_dcm, _mrp_to_dcm, (sigma,)),
        ("dcm_to_mrp", dcm_to_mrp, _dcm_to_mrp, (C,)),
        ("mrp_derivative", mrp_derivative, _mrp_derivative, (sigma, v)),
        ("euler321_to_dcm", euler321_to_dcm, _euler321_to_dcm, (angles,)),
        ("dcm_to_euler321", dcm_to_euler321, _dcm_to_euler321, (C,)),
        ("quat_to_euler321", quat_to_euler321, _quat_to_euler321, (q,)),
        ("euler321_to_quat", euler321_to_quat, _euler321_to_quat, (angles,)),
        ("skew", skew, _skew, (v,)),
        ("safe_norm", safe_norm, _safe_norm, (v,)),
        # A Python scalar does not promote float32.
        (
            "quat_from_axis_angle",
            lambda axis: quat_from_axis_angle(axis, 0.5),
            lambda axis: _quat_from_axis_angle(axis, half),
            (v,),
        ),
    ]


def test_float32_in_float32_out():
    """Every public function traces with float32 inputs (strict promotion) to float32."""
    calls = _all_calls(np.float32)
    assert {name for name, _, _, _ in calls} == set(jaxdyn._rotations.__all__)
    for name, fn, _, args in calls:
        for leaf in jax.tree.leaves(jax.eval_shape(fn, *args)):
            assert leaf.dtype == jnp.float32, name


def test_float32_values_and_gradients():
    """Run the branch-selecting functions in float32: float32 results at float32 accuracy."""
    calls = {name: (fn, reference, args) for name, fn, reference, args in _all_calls(np.float32)}
    names = ["dcm_to_quat", "dcm_to_euler321", "quat_to_axis_angle", "mrp_switch", "safe_norm"]
    identity = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)
    locked = Rotation.from_euler("ZYX", [0.3, np.pi / 2, -0.4]).as_matrix().astype(np.float32)

    @jax.jit
    def evaluate(all_args, C, q, identity, locked):
        values = [calls[name][0](*args) for name, args in zip(names, all_args)]
        derivatives = [
            jax.grad(lambda c: jnp.sum(dcm_to_quat(c)))(C),
            jax.grad(lambda c: jnp.sum(dcm_to_euler321(c)))(C),
            jax.jacobian(dcm_to_euler321)(locked),
            jax.grad(lambda x: jnp.sum(mrp_switch(mrp_from_quat(x))))(q),
            jax.jacobian(quat_to_axis_angle)(identity),
            jax.grad(safe_norm)(jnp.zeros_like(C[0])),
        ]
        return values, derivatives, dcm_to_euler321(locked)

    C = calls["dcm_to_quat"][2][0]
    q = calls["quat_to_axis_angle"][2][0]
    values, derivatives, angles_locked = evaluate(
        [calls[name][2] for name in names], C[0], q[0], identity, locked
    )
    for name, out32 in zip(names, values):
        reference, args32 = calls[name][1], calls[name][2]
        out64 = reference(*(np.asarray(x, dtype=np.float64) for x in args32))
        for leaf32, leaf64 in zip(jax.tree.leaves(out32), jax.tree.leaves(out64), strict=True):
            assert leaf32.dtype == jnp.float32, name
            np.testing.assert_allclose(
                np.asarray(leaf32, dtype=np.float64),
                np.asarray(leaf64),
                rtol=tol(ROUNDOFF, jnp.float32),
                atol=tol(ROUNDOFF, jnp.float32),
                err_msg=name,
            )
    for leaf in jax.tree.leaves(derivatives):
        assert leaf.dtype == jnp.float32
        assert np.all(np.isfinite(np.asarray(leaf)))
    # Gimbal lock in float32: finite, and the angles reproduce the matrix.
    assert angles_locked.dtype == jnp.float32
    rebuilt = Rotation.from_euler("ZYX", np.asarray(angles_locked, dtype=np.float64)).as_matrix()
    _assert_close(rebuilt, locked, tol(ROUNDOFF, jnp.float32))


def test_leading_batch_axes_and_broadcasting():
    rng = np.random.default_rng(23)
    q = _random_unit(rng, N_SAMPLES, 4).reshape(20, 15, 4)
    v = rng.normal(size=(20, 15, 3))
    C = np.asarray(jax.jit(quat_to_dcm)(q))
    _assert_close(C.reshape(-1, 3, 3), _quat_to_dcm(q.reshape(-1, 4)), tol(ROUNDOFF))
    _assert_close(
        np.asarray(jax.jit(dcm_to_quat)(C)).reshape(-1, 4),
        _dcm_to_quat(C.reshape(-1, 3, 3)),
        tol(ROUNDOFF),
    )

    def shape(fn, *args):
        return jax.tree.map(lambda x: x.shape, jax.eval_shape(fn, *args))

    assert shape(quat_to_dcm, q) == (20, 15, 3, 3)
    assert shape(dcm_to_quat, C) == (20, 15, 4)
    assert shape(dcm_to_euler321, C) == (20, 15, 3)
    assert shape(dcm_to_mrp, C) == (20, 15, 3)
    assert shape(quat_to_axis_angle, q) == ((20, 15, 3), (20, 15))
    assert shape(safe_norm, v) == (20, 15)
    # One quaternion against a batch of rates; a batch of axes against one angle.
    assert shape(quat_derivative, q[0, 0], v) == (20, 15, 4)
    assert shape(quat_rotate, q[0, 0], v) == (20, 15, 3)
    assert shape(mrp_derivative, v[0, 0], v) == (20, 15, 3)
    assert shape(quat_from_axis_angle, v, 0.5) == (20, 15, 4)
    assert shape(quat_from_axis_angle, v[0, 0], np.linspace(0.0, 1.0, 5)) == (5, 4)
    assert shape(quat_multiply, q[0, 0], q) == (20, 15, 4)
