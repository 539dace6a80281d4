"""The shared pose-graph pieces (ptm_ros.maps.posegraph): residuals, their sparse Jacobian against finite
differences, and Levenberg–Marquardt on a small graph whose optimum is known."""

from __future__ import annotations

import numpy as np

from ptm_ros.maps.posegraph import RelativeFactors, levenberg_marquardt, relative_jacobian, relative_residuals
from ptm_ros.model.geometry import between, compose


def square_graph(noise: float, seed: int = 0) -> tuple[np.ndarray, RelativeFactors]:
    """Four poses on a 4 m square, odometry between consecutive ones and one loop 3 -> 0."""
    rng = np.random.default_rng(seed)
    true = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, np.pi / 2], [4.0, 4.0, np.pi], [0.0, 4.0, -np.pi / 2]])
    a = np.array([0, 1, 2, 0])
    b = np.array([1, 2, 3, 3])
    z = np.array([between(true[i], true[j]) for i, j in zip(a, b, strict=True)])
    z += rng.normal(0.0, noise, z.shape)
    w = np.broadcast_to(np.diag([10.0, 10.0, 30.0]), (4, 3, 3)).copy()
    return true, RelativeFactors(a=a, b=b, z=z, w=w)


def test_jacobian_matches_finite_differences():
    true, f = square_graph(0.0)
    x = true + np.random.default_rng(1).normal(0.0, 0.2, true.shape)
    x[0] = true[0]
    r, tx, ty = relative_residuals(x, f)
    jac = relative_jacobian(x, f, tx, ty).toarray()
    assert jac.shape == (12, 9)
    eps = 1e-7
    for k in range(9):
        dx = x.copy()
        dx[1 + k // 3, k % 3] += eps
        numeric = (relative_residuals(dx, f)[0] - r).ravel() / eps
        np.testing.assert_allclose(jac[:, k], numeric, atol=1e-5)


def test_levenberg_marquardt_recovers_the_consistent_graph():
    true, f = square_graph(0.0)
    start = np.array([compose(p, [0.3, -0.2, 0.1]) for p in true])
    start[0] = true[0]

    def cost(x):
        return 0.5 * float(np.sum(relative_residuals(x, f)[0] ** 2))

    def normal(x):
        r, tx, ty = relative_residuals(x, f)
        jac = relative_jacobian(x, f, tx, ty)
        return (jac.T @ jac).tocsc(), jac.T @ r.ravel()

    x = levenberg_marquardt(start, cost, normal, max_iterations=50, tolerance=1e-14)
    assert cost(x) < 1e-12
    np.testing.assert_allclose(x[:, :2], true[:, :2], atol=1e-6)
    assert np.array_equal(x[0], true[0])  # the gauge stays fixed
