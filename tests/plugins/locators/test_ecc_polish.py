"""The ECC polish of the feature locators counts only pixels trusted in both frames."""

import numpy as np
from locator_cases import DATA
from photonpano import geometry
from photonpano.plugins.locators.polish import ecc_polish

W, H = 248, 160


def test_untrusted_pixels_of_the_moving_frame_do_not_pull_the_polish():
    """Frame a's left third is unobserved (0 in its ECC image).

    Before session 3 the polish passed frame b's mask as OpenCV's ``inputMask``, which
    OpenCV applies to the *input* image (frame a): a's unobserved pixels were correlated
    with b's texture. That case is reproduced below by calling with a's mask all True.
    """
    import cv2

    photo = cv2.imread(str(DATA / "source.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
    crop = geometry.translation(-180.0, -140.0)
    motion = geometry.translation(1.6, -0.9)
    truth = crop @ np.linalg.inv(motion) @ np.linalg.inv(crop)  # b's pixels to a's
    b = cv2.warpPerspective(photo, crop, (W, H), flags=cv2.INTER_CUBIC)
    a = cv2.warpPerspective(photo, crop @ np.linalg.inv(motion), (W, H), flags=cv2.INTER_CUBIC)
    mask_a = np.ones((H, W), bool)
    mask_a[:, : W // 3] = False
    a[~mask_a] = 0.0
    start = truth @ geometry.translation(0.6, 0.4)
    c = geometry.corners(W, H)

    def error(h):
        return float(np.abs(geometry.apply(h, c) - geometry.apply(truth, c)).max())

    both = ecc_polish(a, b, mask_a, np.ones((H, W), bool), start, blur=5)
    b_only = ecc_polish(a, b, np.ones((H, W), bool), np.ones((H, W), bool), start, blur=5)
    assert error(both) < 0.1, f"{error(both):.3f} px"
    assert error(b_only) > 2 * error(both)
