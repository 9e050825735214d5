"""SE(3) helpers, quaternion conventions and the Kabsch fit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from perception import geometry as g

finite = st.floats(-100, 100, allow_nan=False, allow_infinity=False)
seeds = st.integers(0, 2**32 - 1)


def random_T(rng: np.random.Generator, scale: float = 10.0) -> np.ndarray:
    return g.make_T(Rotation.random(random_state=rng), rng.uniform(-scale, scale, 3))


@given(seeds)
def test_invert_is_inverse(seed: int) -> None:
    T = random_T(np.random.default_rng(seed))
    np.testing.assert_allclose(g.compose(T, g.invert(T)), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(g.invert(T), np.linalg.inv(T), atol=1e-10)


@given(seeds)
def test_composition_matches_sequential_application(seed: int) -> None:
    rng = np.random.default_rng(seed)
    A, B = random_T(rng), random_T(rng)
    p = rng.normal(size=(17, 3))
    np.testing.assert_allclose(
        g.transform_points(g.compose(A, B), p), g.transform_points(A, g.transform_points(B, p)),
        atol=1e-10,
    )
    assert g.is_rigid(g.compose(A, B))


@given(seeds)
def test_quaternion_round_trip_scalar_first_canonical(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng).as_matrix()
    q = g.matrix_to_quat(R)
    assert q.shape == (4,) and q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(g.quat_to_matrix(q), R, atol=1e-12)
    np.testing.assert_allclose(g.quat_to_matrix(-q), R, atol=1e-12)  # double cover


def test_quaternion_convention_is_hamilton_scalar_first() -> None:
    # 90 deg about +z: (cos 45, 0, 0, sin 45) maps x onto y.
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(g.quat_to_matrix(q) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    with pytest.raises(ValueError, match="quaternion"):
        g.quat_to_matrix([0, 0, 0, 0])


@given(seeds)
def test_se3_exp_log_round_trip(seed: int) -> None:
    rng = np.random.default_rng(seed)
    xi = np.concatenate([rng.uniform(-5, 5, 3), rng.uniform(-1, 1, 3) * 1.7])  # |phi| < pi: log is unique
    np.testing.assert_allclose(g.se3_log(g.se3_exp(xi)), xi, atol=1e-9)


@settings(max_examples=60)
@given(seeds, st.integers(3, 200))
def test_kabsch_recovers_random_rigid_transform(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    T = random_T(rng)
    src = rng.normal(size=(n, 3)) * rng.uniform(0.5, 20)
    dst = g.transform_points(T, src)
    T_est = g.kabsch(src, dst)
    np.testing.assert_allclose(T_est, T, atol=1e-9)


@given(seeds)
def test_kabsch_weighted_and_reflection_safe(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = random_T(rng)
    # Planar points: the SVD alone could return a reflection; the fit must stay proper.
    src = np.column_stack([rng.normal(size=(30, 2)), np.zeros(30)])
    dst = g.transform_points(T, src)
    w = rng.uniform(0.1, 2.0, 30)
    outliers = dst.copy()
    outliers[:5] += 50.0
    w_out = w.copy()
    w_out[:5] = 0.0  # zero weight removes the outliers exactly
    T_est = g.kabsch(src, outliers, w_out)
    assert np.linalg.det(T_est[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(T_est, T, atol=1e-8)


def test_kabsch_bad_input_named() -> None:
    with pytest.raises(ValueError, match="needs >= 3"):
        g.kabsch(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        g.kabsch(np.full((4, 3), np.nan), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="matching"):
        g.kabsch(np.zeros((4, 3)), np.zeros((5, 3)))


def test_pose_error_units() -> None:
    T_true = g.make_T(None, [1.0, 2.0, 3.0])
    T_est = g.make_T(Rotation.from_euler("z", 2.0, degrees=True), [1.0, 2.0, 3.05])
    dt, dr = g.pose_error(T_est, T_true)
    assert dt == pytest.approx(0.05)
    assert dr == pytest.approx(2.0)


def test_is_rigid_matches_the_allclose_definition_at_the_tolerance() -> None:
    """The written-out check gives allclose's answer on transforms perturbed around ``tol``."""

    def reference(T: np.ndarray, tol: float) -> bool:
        R = T[:3, :3]
        return bool(np.all(np.isfinite(T)) and np.allclose(R.T @ R, np.eye(3), atol=tol)
                    and abs(np.linalg.det(R) - 1.0) < tol and np.allclose(T[3], [0, 0, 0, 1], atol=tol))

    rng = np.random.default_rng(4)
    answers = []
    for k in range(2000):
        T = g.make_T(Rotation.random(random_state=k).as_matrix(), rng.normal(size=3))
        tol = 10.0 ** rng.uniform(-9, -3)
        T = T + rng.normal(size=(4, 4)) * tol * rng.uniform(0.0, 1.0)
        if k % 7 == 0:
            T[:3, :3] *= -1.0  # improper
        answers.append(reference(T, tol))
        assert g.is_rigid(T, tol) == answers[-1], (k, tol)
    assert 0.1 < np.mean(answers) < 0.9  # both outcomes exercised


def test_check_rigid_names_argument() -> None:
    with pytest.raises(ValueError, match="init_T"):
        g.check_rigid(np.diag([2.0, 1, 1, 1]), "init_T")
    with pytest.raises(ValueError, match="init_T has non-finite"):
        g.check_rigid(np.full((4, 4), np.nan), "init_T")
