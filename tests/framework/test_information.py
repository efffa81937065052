"""The information of a registration about the 8 homography parameters, and the shift it corrects."""

import cv2
import numpy as np
import pytest
from photonpano import geometry
from photonpano.information import (
    SHAPE,
    SHIFT,
    conditional_shift,
    homography_information,
    information_in_sensor_pixels,
)


def _texture(h=120, w=200, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 2.0)


def test_information_equals_the_sum_over_pixels():
    """The moments give ``sum_x J' J`` exactly (J: gradient times the warp's Jacobian about the centre)."""
    image = _texture()
    mask = np.ones(image.shape, bool)
    mask[:6] = False
    mask[:, -9:] = False
    fast = homography_information(image[None], mask[None], blur_px=0)[0]
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=1) * 0.5
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=1) * 0.5
    inside = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0) > 0
    h, w = image.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xs - (w - 1) / 2, ys - (h - 1) / 2
    zero, one = np.zeros_like(x), np.ones_like(x)
    jx = np.stack([x, zero, y, zero, one, zero, -x * x, -x * y], -1)
    jy = np.stack([zero, x, zero, y, zero, one, -x * y, -y * y], -1)
    jacobian = (gx[..., None] * jx + gy[..., None] * jy)[inside]
    np.testing.assert_allclose(fast, jacobian.T @ jacobian, rtol=1e-9, atol=1e-9 * np.abs(fast).max())


def test_the_shift_given_the_true_shape_is_more_precise():
    """Least-squares registrations of noisy images: correcting each shift with the true shape cuts its error.

    Gauss-Newton on the 8 parameters from the identity (the Lucas-Kanade step of Baker
    and Matthews), 200 noisy copies of a texture; the conditional shift given the true
    (zero) shape is closer to the truth than the 8-parameter shift, as the information
    predicts.
    """
    image = _texture(seed=3).astype(np.float64)
    h, w = image.shape
    mask = np.ones((h, w), bool)
    information = homography_information(image[None], mask[None], blur_px=0)[0]
    gx = cv2.Sobel(image, cv2.CV_64F, 1, 0, ksize=1) * 0.5
    gy = cv2.Sobel(image, cv2.CV_64F, 0, 1, ksize=1) * 0.5
    inside = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0) > 0
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xs - (w - 1) / 2, ys - (h - 1) / 2
    zero, one = np.zeros_like(x), np.ones_like(x)
    jx = np.stack([x, zero, y, zero, one, zero, -x * x, -x * y], -1)
    jy = np.stack([zero, x, zero, y, zero, one, -x * y, -y * y], -1)
    jacobian = (gx[..., None] * jx + gy[..., None] * jy)[inside]  # (N, 8)
    rng = np.random.default_rng(0)
    plain, conditioned = [], []
    for _ in range(200):
        noise = rng.normal(0, 0.02, jacobian.shape[0])
        estimate = np.linalg.solve(information, jacobian.T @ noise)  # one Gauss-Newton step: the error
        plain.append(estimate[SHIFT])
        conditioned.append(estimate[SHIFT] + conditional_shift(information[None], estimate[SHAPE][None])[0])
    plain_rms, conditioned_rms = np.sqrt(np.mean(np.square(plain))), np.sqrt(np.mean(np.square(conditioned)))
    predicted = np.sqrt(np.trace(np.linalg.inv(information[np.ix_(SHIFT, SHIFT)])) / 2) * 0.02
    assert conditioned_rms < 0.8 * plain_rms, (conditioned_rms, plain_rms)  # measured: 0.0085 against 0.0110
    assert conditioned_rms == pytest.approx(predicted, rel=0.15)  # inv(F_tt): 0.0094


def test_no_texture_changes_nothing_and_binning_rescales():
    flat = np.ones((1, 40, 60), np.float32)
    information = homography_information(flat, np.ones(flat.shape, bool))
    assert np.all(information == 0)
    assert np.all(conditional_shift(information, np.ones((1, 6))) == 0)
    image = _texture()
    binned = cv2.resize(image, (100, 60), interpolation=cv2.INTER_AREA)
    sensor = homography_information(image[None], np.ones((1,) + image.shape, bool))[0]
    rescaled = information_in_sensor_pixels(homography_information(binned[None], np.ones((1, 60, 100), bool))[0:1],
                                            2)[0]
    # the shift's coupling to the perspective, inv(F_tt) F_ts (the x^2 and x y terms, whose mean over the
    # frame is not zero: the coupling that matters), agrees between the two in sensor units
    perspective = [4, 5]  # p7, p8 among the shape's columns
    coupling = np.linalg.solve(sensor[np.ix_(SHIFT, SHIFT)], sensor[np.ix_(SHIFT, SHAPE)])[:, perspective]
    coupling_binned = np.linalg.solve(rescaled[np.ix_(SHIFT, SHIFT)], rescaled[np.ix_(SHIFT, SHAPE)])[:, perspective]
    np.testing.assert_allclose(np.diag(coupling_binned), np.diag(coupling), rtol=0.15)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="homography_information"):
        homography_information(np.zeros((2, 10, 10)), np.ones((2, 10, 11), bool))
    assert geometry  # the module's parameter order is geometry's p1..p8
