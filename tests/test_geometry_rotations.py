"""Property tests for sc6d_jax.geometry rotations (float64 via a module-scoped x64 fixture)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sc6d_jax import geometry as g

SETTINGS = settings(max_examples=15, deadline=None)
B = 8  # fixed batch size: one compilation per function


@pytest.fixture(autouse=True, scope="module")
def x64():
    """Enable float64 for this module only, restoring the previous setting afterwards."""
    with jax.enable_x64(True):
        yield


finite = st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)
quats = arrays(np.float64, (B, 4), elements=finite).filter(lambda q: np.all(np.linalg.norm(q, axis=-1) > 0.1))
# angles concentrated on the hard cases: 0, tiny, near pi, exactly pi
angles = st.one_of(
    st.floats(0.0, np.pi),
    st.sampled_from([0.0, 1e-12, 1e-8, 1e-5, 1e-3, np.pi - 1e-3, np.pi - 1e-7, np.pi - 1e-10, np.pi]),
)
axes = arrays(np.float64, (3,), elements=finite).filter(lambda v: np.linalg.norm(v) > 0.1)


def rotations(q: np.ndarray) -> jnp.ndarray:
    return g.quat_to_matrix(jnp.asarray(q))


def assert_rotation(R, tol: float = 1e-12) -> None:
    R = np.asarray(R)
    if R.size == 0:
        return
    assert np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max() < tol
    assert np.abs(np.linalg.det(R) - 1).max() < tol


@SETTINGS
@given(quats)
def test_quat_roundtrip(q):
    R = rotations(q)
    assert R.dtype == jnp.float64
    assert_rotation(R)
    q2 = np.asarray(g.matrix_to_quat(R))
    qn = q / np.linalg.norm(q, axis=-1, keepdims=True)
    assert np.all(q2[:, 0] >= 0)
    # equal up to the sign ambiguity q ~ -q
    err = np.minimum(np.abs(q2 - qn).max(-1), np.abs(q2 + qn).max(-1))
    assert err.max() < 1e-12
    np.testing.assert_allclose(g.quat_to_matrix(q2), R, atol=1e-13)


@SETTINGS
@given(axes, angles)
def test_axis_angle_roundtrip(axis, angle):
    aa = axis / np.linalg.norm(axis) * angle
    R = g.axis_angle_to_matrix(jnp.asarray(aa))
    assert_rotation(R)
    aa2 = np.asarray(g.matrix_to_axis_angle(R))
    assert np.linalg.norm(aa2) <= np.pi + 1e-12
    np.testing.assert_allclose(g.axis_angle_to_matrix(aa2), R, atol=1e-12)
    if angle < np.pi - 1e-6:
        # far from pi the vector is unique; tiny angles are recovered to full relative precision
        np.testing.assert_allclose(aa2, aa, rtol=1e-9, atol=1e-15)
    # agrees with the quaternion route
    half = angle / 2
    q = np.concatenate([[np.cos(half)], np.sin(half) * axis / np.linalg.norm(axis)])
    np.testing.assert_allclose(g.quat_to_matrix(q), R, atol=1e-14)


@SETTINGS
@given(quats, arrays(np.float64, (B, 6), elements=st.floats(-3, 3)))
def test_sixd_roundtrip_and_gram_schmidt(q, x):
    R = rotations(q)
    np.testing.assert_allclose(g.sixd_to_matrix(g.matrix_to_sixd(R)), R, atol=1e-13)
    a1, a2 = x[:, :3], x[:, 3:]
    ok = (np.linalg.norm(a1, axis=-1) > 0.1) & (np.linalg.norm(np.cross(a1, a2), axis=-1) > 0.1)
    Rx = np.asarray(g.sixd_to_matrix(x))[ok]
    assert_rotation(Rx)
    # first column is a1's direction, second lies in span(a1, a2) on a2's side
    np.testing.assert_allclose(Rx[:, :, 0], a1[ok] / np.linalg.norm(a1[ok], axis=-1, keepdims=True), atol=1e-12)
    assert np.all(np.einsum("bi,bi->b", Rx[:, :, 1], a2[ok]) > 0)
    np.testing.assert_allclose(np.einsum("bi,bi->b", Rx[:, :, 2], a2[ok]), 0, atol=1e-12)


@SETTINGS
@given(quats, quats, arrays(np.float64, (B, 3, 3), elements=st.floats(-1, 1)))
def test_project_to_so3(q1, q2, M):
    R = rotations(q1)
    np.testing.assert_allclose(g.project_to_so3(R), R, atol=1e-12)
    # well-conditioned inputs (unique nearest rotation): orthonormal, det +1, equivariant, optimal
    P = np.asarray(g.project_to_so3(M))
    sv = np.linalg.svd(M, compute_uv=False)
    ok = (sv[:, 2] > 1e-2) & (sv[:, 1] - sv[:, 2] > 1e-2)
    assert_rotation(P[ok], tol=1e-10)
    # a reflection of a rotation is mapped to a proper rotation
    assert np.all(np.linalg.det(np.asarray(g.project_to_so3(-R))) > 0.999)
    # equivariance: proj(Ra M Rb) = Ra proj(M) Rb, and optimality against nearby rotations
    Ra, Rb = np.asarray(R), np.asarray(rotations(q2))
    np.testing.assert_allclose(g.project_to_so3(Ra @ M @ Rb)[ok], (Ra @ P @ Rb)[ok], atol=1e-9)
    d_best = np.linalg.norm(M - P, axis=(-1, -2))
    for eps in (1e-3, 1e-2):
        Q = P @ np.asarray(g.axis_angle_to_matrix(eps * np.ones((B, 3))))
        assert np.all(d_best[ok] <= np.linalg.norm(M - Q, axis=(-1, -2))[ok] + 1e-12)


@SETTINGS
@given(quats, axes, angles)
def test_geodesic_angle_accurate_near_0_and_pi(q, axis, angle):
    R1 = rotations(q)
    D = g.axis_angle_to_matrix(jnp.asarray(axis / np.linalg.norm(axis) * angle))
    R2 = R1 @ D
    got = np.asarray(g.geodesic_angle(R1, R2))
    assert np.all((got >= 0) & (got <= np.pi))
    np.testing.assert_allclose(got, angle, rtol=1e-7, atol=3e-15)
    np.testing.assert_allclose(g.geodesic_angle(R2, R1), got, atol=1e-15)
    # invariance under a common left rotation
    np.testing.assert_allclose(g.geodesic_angle(R1[::-1] @ R1, R1[::-1] @ R2), got, atol=1e-12)


def test_axis_rotations_match_axis_angle():
    a = jnp.linspace(-4, 4, 9)
    for fn, e in ((g.rot_x, 0), (g.rot_y, 1), (g.rot_z, 2)):
        aa = jnp.zeros((9, 3)).at[:, e].set(a)
        np.testing.assert_allclose(fn(a), g.axis_angle_to_matrix(aa), atol=1e-14)
    assert g.rot_z(jnp.zeros((2, 5))).shape == (2, 5, 3, 3)
    np.testing.assert_allclose(g.rot_x(np.pi / 2) @ np.array([0.0, 1, 0]), [0, 0, 1], atol=1e-15)


@SETTINGS
@given(axes, axes, st.sampled_from([None, "parallel", "antiparallel", "nearly-antiparallel"]))
def test_rotation_between(a, b, case):
    if case == "parallel":
        b = 2 * a
    elif case == "antiparallel":
        b = -3 * a
    elif case == "nearly-antiparallel":
        b = -a + 1e-9 * np.cross(a, [0.3, -0.2, 0.9])
    R = g.rotation_between(jnp.asarray(a), jnp.asarray(b))
    assert_rotation(R)
    np.testing.assert_allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-12)
    if case is None:  # minimal: the angle equals the angle between a and b
        ang = np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))
        np.testing.assert_allclose(g.geodesic_angle(jnp.eye(3), R), ang, atol=1e-7)


def test_float32_batched_jit_and_dtype():
    key = jax.random.key(1)
    R = g.random_rotations(key, 6, jnp.float32).reshape(2, 3, 3, 3)
    assert R.dtype == jnp.float32
    outs = {
        "quat": g.matrix_to_quat(R),
        "aa": g.matrix_to_axis_angle(R),
        "sixd": g.matrix_to_sixd(R),
        "proj": g.project_to_so3(R),
        "geo": g.geodesic_angle(R, R),
        "R_q": g.quat_to_matrix(g.matrix_to_quat(R)),
        "R_aa": g.axis_angle_to_matrix(g.matrix_to_axis_angle(R)),
        "R_6": g.sixd_to_matrix(g.matrix_to_sixd(R)),
    }
    shapes = {"quat": (2, 3, 4), "aa": (2, 3, 3), "sixd": (2, 3, 6), "geo": (2, 3)}
    for name, out in outs.items():
        assert out.dtype == jnp.float32, name
        assert out.shape == shapes.get(name, (2, 3, 3, 3)), name
    for name in ("proj", "R_q", "R_aa", "R_6"):
        np.testing.assert_allclose(outs[name], R, atol=2e-6)
    np.testing.assert_allclose(outs["geo"], 0, atol=1e-3)  # float32: sqrt of rounding noise
    jitted = jax.jit(lambda R: g.matrix_to_axis_angle(g.project_to_so3(R)))
    np.testing.assert_allclose(jitted(R), outs["aa"], atol=1e-5)
    # integer input is promoted to float
    assert jnp.issubdtype(g.rot_z(jnp.array(1)).dtype, jnp.floating)


def test_shape_errors():
    with pytest.raises(ValueError, match="q must have shape"):
        g.quat_to_matrix(jnp.zeros(3))
    with pytest.raises(ValueError, match="R must have shape"):
        g.matrix_to_quat(jnp.zeros((3, 4)))
    with pytest.raises(ValueError, match="x must have shape"):
        g.sixd_to_matrix(jnp.zeros(9))
    with pytest.raises(ValueError, match="R2 must have shape"):
        g.geodesic_angle(jnp.eye(3), jnp.zeros(9))


def test_gradients_are_finite_at_singular_points():
    """Losses may differentiate through these at identity / pi / along the optical axis."""
    eye = jnp.eye(3)
    checks = {
        "geodesic@0": jax.grad(lambda R: g.geodesic_angle(eye, R))(eye),
        "geodesic@pi": jax.grad(lambda R: g.geodesic_angle(eye, R))(g.rot_x(jnp.pi)),
        "aa@0": jax.jacobian(g.axis_angle_to_matrix)(jnp.zeros(3)),
        "log@0": jax.jacobian(g.matrix_to_axis_angle)(eye),
        "sixd": jax.jacobian(g.sixd_to_matrix)(jnp.array([1.0, 0, 0, 0, 1, 0])),
        "ray@axis": jax.jacobian(g.ray_rotation)(jnp.array([0.0, 0, 500])),
    }
    for name, grad in checks.items():
        assert np.all(np.isfinite(np.asarray(grad))), name
    # the exp map's Jacobian at 0 is the generator basis
    np.testing.assert_allclose(checks["aa@0"][..., 0], g.skew(jnp.array([1.0, 0, 0])), atol=1e-12)
