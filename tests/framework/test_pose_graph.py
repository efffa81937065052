"""The level-1 pose graph (posegraph.refine_keyframes) on a long synthetic pan."""

import numpy as np
import pytest
from photonpano import geometry
from photonpano.posegraph import pairs_at_offsets, refine_keyframes
from photonpano.stages import PairRegistrations


def test_long_pan_is_recovered_without_shrinking_the_keyframes():
    """400 keyframes panning 2 px each (800 px), pairs at offsets 1..64 with 0.05 px noise.

    With residuals measured on the panorama the solver could shrink every keyframe (all
    residuals shrink with them): at 200 000 frames 399 of 400 keyframes came out
    implausible, and here the error stayed at 1.04 px. Measured in frame pixels it
    reaches the noise floor.
    """
    rng = np.random.default_rng(1)
    g, width, height = 400, 496, 254
    params = np.zeros((g, 8))
    params[:, :4] = rng.normal(0, 1e-3, (g, 4))
    params[:, 4] = 2.0 * np.arange(g) + rng.normal(0, 2, g)
    params[:, 5] = rng.normal(0, 2, g)
    params[:, 6:] = rng.normal(0, 1e-7, (g, 2))
    truth = geometry.homographies_from_params(params)
    truth[0] = np.eye(3)
    index = pairs_at_offsets(g, (1, 2, 4, 8, 16, 32, 64))
    noise = geometry.homographies_from_params(
        rng.normal(0, [1e-4, 1e-4, 1e-4, 1e-4, 0.05, 0.05, 1e-8, 1e-8], (len(index), 8)))
    measured = np.linalg.inv(truth[index[:, 0]]) @ truth[index[:, 1]] @ noise
    pairs = PairRegistrations(measured, np.full(len(index), 100), np.full(len(index), 100),
                              np.ones(len(index), bool))
    start = truth @ geometry.homographies_from_params(
        rng.normal(0, [1e-3, 1e-3, 1e-3, 1e-3, 1, 1, 1e-7, 1e-7], (g, 8)))
    start[0] = truth[0]
    solved = refine_keyframes(start, index, pairs, width, height)
    corners = geometry.corners(width, height)
    before = np.abs(geometry.apply(start, corners) - geometry.apply(truth, corners)).max()
    after = np.abs(geometry.apply(solved, corners) - geometry.apply(truth, corners)).max()
    assert before > 3.0
    assert after < 0.3, f"largest corner error {after:.3f} px"


@pytest.mark.parametrize("compiled", [True, False], ids=["banded-kernel", "numpy-entries"])
def test_pair_jacobian_normal_equations_equal_the_dense_products(compiled, monkeypatch):
    """Block-by-block assembly == J^T W J and J^T W r of the dense Jacobian (fixed block -1, repeated pairs).

    Both assemblies: the compiled one straight into the band, and the numpy one by
    entries (taken when the band would exceed ``MAX_BAND_BYTES``).
    """
    from photonpano import posegraph
    from photonpano.posegraph import NormalMatrix, PairJacobian

    if not compiled:
        monkeypatch.setattr(posegraph, "MAX_BAND_BYTES", 0)

    rng = np.random.default_rng(3)
    e, r, d, blocks = 40, 6, 3, 7
    first_block, second_block = rng.integers(-1, blocks, e), rng.integers(-1, blocks, e)
    first, second = rng.normal(size=(e, r, d)), rng.normal(size=(e, r, d))
    weights, residual = rng.uniform(0.1, 1, e * r), rng.normal(size=e * r)
    dense = np.zeros((e * r, blocks * d))
    for k in range(e):
        for jac, block in ((first[k], first_block[k]), (second[k], second_block[k])):
            if block >= 0:
                dense[k * r:(k + 1) * r, block * d:(block + 1) * d] += jac
    normal, gradient = PairJacobian(first, second, first_block, second_block, blocks).normal_equations(
        weights, residual)
    expected = dense.T @ (weights[:, None] * dense)
    np.testing.assert_allclose(gradient, dense.T @ (weights * residual), atol=1e-12)
    np.testing.assert_allclose(normal.diagonal, np.diag(expected), atol=1e-12)
    damping, rhs = rng.uniform(0.5, 1, blocks * d), rng.normal(size=blocks * d)
    solution = np.linalg.solve(expected + np.diag(damping), rhs)
    np.testing.assert_allclose(normal.solve(damping, rhs), solution, atol=1e-9)
    sparse = NormalMatrix(*normal.entries(), blocks * d, max_band_bytes=0)  # SuperLU
    np.testing.assert_allclose(sparse.solve(damping, rhs), solution, atol=1e-9)


def test_compiled_pair_residuals_have_the_jacobians_of_finite_differences():
    """The pose graph's compiled residuals: zero at the truth, derivatives equal to central differences."""
    from photonpano._posegraph_compiled import pair_residuals

    rng = np.random.default_rng(5)
    g, width, height = 6, 496, 254
    keyframes = geometry.homographies_from_params(rng.normal(0, [1e-3] * 4 + [20, 20, 1e-6, 1e-6], (g, 8)))
    keyframes[0] = np.eye(3)
    a, b = np.array([0, 1, 2, 0, 3]), np.array([1, 2, 5, 4, 5])
    gx, gy = np.meshgrid(np.linspace(0, width - 1, 3), np.linspace(0, height - 1, 3))
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    relative0 = np.linalg.inv(keyframes[a]) @ keyframes[b]
    mapped = geometry.apply(relative0, grid)
    weight = rng.uniform(0.5, 2, len(a))
    residual, ja, jb = pair_residuals(np.zeros((g - 1) * 8), relative0, mapped, grid, weight, a, b)
    assert np.abs(residual).max() < 1e-9
    free = rng.normal(0, [1e-4] * 4 + [0.5, 0.5, 1e-8, 1e-8], (g - 1, 8)).ravel()
    residual, ja, jb = pair_residuals(free, relative0, mapped, grid, weight, a, b)
    # the residual is the weighted measured point minus frame a's point after both updates
    updates = geometry.homographies_from_params(np.concatenate([np.zeros((1, 8)), free.reshape(g - 1, 8)]))
    moved = geometry.apply(np.linalg.inv(updates[a]) @ relative0 @ updates[b], grid)
    np.testing.assert_allclose(residual, ((mapped - moved) * weight[:, None, None]).ravel(), atol=1e-9)
    steps = np.array([1e-7] * 4 + [1e-4, 1e-4, 1e-10, 1e-10])
    for block, jac in ((a, ja), (b, jb)):
        for k in range(8):
            numeric = np.zeros_like(jac[..., k])
            for e in range(len(a)):
                if block[e] == 0:
                    continue  # the gauge keyframe has no unknowns
                shifted = [free.copy(), free.copy()]
                shifted[0][8 * (block[e] - 1) + k] += steps[k]
                shifted[1][8 * (block[e] - 1) + k] -= steps[k]
                plus, minus = (pair_residuals(f, relative0, mapped, grid, weight, a, b)[0] for f in shifted)
                numeric[e] = (plus - minus).reshape(len(a), 18)[e] / (2 * steps[k])
            free_rows = block > 0  # rows of the gauge keyframe are not used (PairJacobian block -1)
            scale = np.abs(jac[free_rows, :, k]).max()
            np.testing.assert_allclose(jac[free_rows, :, k], numeric[free_rows], atol=1e-5 * scale,
                                       err_msg=f"parameter p{k + 1}")
