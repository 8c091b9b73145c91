"""cdpr.compiled_linalg's kernels against scipy's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import null_space

from cdpr.compiled_linalg import left_null_space


@pytest.mark.parametrize("shape", [(8, 6), (7, 6), (12, 6), (4, 3)])
def test_the_left_null_space_is_scipy_s(shape: tuple[int, int]) -> None:
    """Full-rank matrices: N spans what scipy.linalg.null_space(A^T) spans (the same
    projector N N^T), orthonormal, orthogonal to A's columns."""
    rows, cols = shape
    rng = np.random.default_rng(rows * cols)
    for _ in range(50):
        A = rng.normal(size=shape)
        N = np.empty((rows, rows - cols))
        left_null_space(A, N)
        reference = null_space(A.T)
        np.testing.assert_allclose(N @ N.T, reference @ reference.T, atol=1e-12)
        np.testing.assert_allclose(N.T @ N, np.eye(rows - cols), atol=1e-12)
        np.testing.assert_allclose(N.T @ A, 0.0, atol=1e-12)


def test_a_rank_deficient_matrix_still_gets_an_orthonormal_basis_in_its_null_space() -> None:
    """A column that is a combination of others, or zero (a singular pose): N is still
    orthonormal and within scipy's (larger) left null space."""
    rng = np.random.default_rng(3)
    for column in range(6):
        A = rng.normal(size=(8, 6))
        A[:, column] = 0.0 if column % 2 else A[:, (column + 1) % 6] - 2.0 * A[:, (column + 2) % 6]
        N = np.empty((8, 2))
        left_null_space(A, N)
        reference = null_space(A.T)
        assert reference.shape[1] == 3
        np.testing.assert_allclose(N.T @ N, np.eye(2), atol=1e-12)
        np.testing.assert_allclose(reference @ (reference.T @ N), N, atol=1e-12)
