import numpy as np
import pytest
from photonpano import geometry


def test_params_roundtrip_and_identity():
    rng = np.random.default_rng(0)
    h = np.eye(3) + rng.normal(scale=[[1e-2, 1e-2, 3], [1e-2, 1e-2, 3], [1e-5, 1e-5, 0]], size=(5, 3, 3))
    h[:, 2, 2] = 1
    p = geometry.params_from_homographies(h)
    assert p.shape == (5, 8)
    np.testing.assert_allclose(geometry.homographies_from_params(p), h, atol=1e-12)
    np.testing.assert_array_equal(geometry.params_from_homographies(np.eye(3)[None]), np.zeros((1, 8)))


def test_params_follow_paper_eq4_layout():
    # H = [[1+p1, p3, p5], [p2, 1+p4, p6], [p7, p8, 1]]
    p = np.arange(1, 9, dtype=float)[None] / 100
    h = geometry.homographies_from_params(p)[0]
    expected = [[1.01, 0.03, 0.05], [0.02, 1.04, 0.06], [0.07, 0.08, 1]]
    np.testing.assert_allclose(h, expected)


def test_normalize_rejects_degenerate():
    with pytest.raises(ValueError, match="degenerate"):
        geometry.normalize(np.zeros((3, 3)))


def test_scale_matrix_keeps_pixel_edges():
    # With pixel centres at integers, the outer edges -0.5 and W-0.5 map to -0.5 and sW-0.5.
    s = geometry.scale_matrix(2.0)
    edges = geometry.apply(s, np.array([[-0.5, -0.5], [9.5, 4.5]]))
    np.testing.assert_allclose(edges, [[-0.5, -0.5], [19.5, 9.5]])


def test_footprint_bounds_of_translation():
    h = geometry.translation(10, -3)[None]
    assert geometry.footprint_bounds(h, 8, 4) == (9.5, -3.5, 17.5, 0.5)


def test_invert_equals_numpy_inverse():
    """The closed-form inverse of a stack of homographies equals np.linalg.inv to rounding."""
    rng = np.random.default_rng(2)
    h = geometry.homographies_from_params(rng.normal(0, [1e-2] * 4 + [200, 100] + [1e-5] * 2, (500, 8)))
    np.testing.assert_allclose(geometry.invert(h), np.linalg.inv(h), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(geometry.invert(h[0]) @ h[0], np.eye(3), atol=1e-12)


def test_about_centre_puts_the_origin_at_the_frame_centre():
    # a rotation about the frame centre: no displacement of the centre (p5 = p6 = 0) about it
    w, h = 496, 254
    cx, cy = (w - 1) / 2, (h - 1) / 2
    angle = 0.01
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1.0]])
    about_pixel_origin = geometry.translation(cx, cy) @ rotation @ geometry.translation(-cx, -cy)
    params = geometry.params_from_homographies(geometry.about_centre(about_pixel_origin[None], w, h))[0]
    np.testing.assert_allclose(params[4:6], 0, atol=1e-12)
    np.testing.assert_allclose(params[[1, 2]], [np.sin(angle), -np.sin(angle)], atol=1e-12)
    np.testing.assert_allclose(geometry.from_centre(geometry.about_centre(about_pixel_origin, w, h), w, h),
                               about_pixel_origin, atol=1e-12)
