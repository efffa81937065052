"""pycolmap-sfm's track refinement: Lucas-Kanade re-location of keypoints and outlier pruning."""

import importlib.util

import numpy as np
import pytest

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("pycolmap") is None,
    reason="pycolmap is not installed (pip install 'photonpano[colmap]')",
)

SHAPE = (120, 160)
K = (200.0, 80.5, 60.5)  # f, cx, cy (COLMAP convention, centres at +0.5)


def _texture(seed):
    import cv2

    noise = np.random.default_rng(seed).uniform(0, 255, SHAPE).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 2.0)


def _scene(shift, noise_px, seed=0):
    """Three views of a fronto-parallel textured plane at depth 1, the camera translating along x.

    The views are the texture shifted by 0, shift and 2 shift pixels; keypoints are the true
    projections of a grid of points plus Gaussian noise (like SIFT's localisation error).
    Returns the reconstruction, the images by id and the true keypoints by image id.
    """
    import cv2
    import pycolmap

    base, rng = _texture(seed), np.random.default_rng(seed + 1)
    f, cx, cy = K
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=SHAPE[1], height=SHAPE[0], params=[f, cx, cy], camera_id=1)
    rec.add_camera_with_trivial_rig(camera)
    grid = np.stack(np.meshgrid(np.arange(25, 136, 12.0), np.arange(25, 96, 12.0)), -1).reshape(-1, 2) + 0.5
    world = np.column_stack([(grid[:, 0] - cx) / f, (grid[:, 1] - cy) / f, np.ones(len(grid))])
    images, truth = {}, {}
    for view in range(3):
        dx = view * shift
        warp = np.float32([[1, 0, -dx], [0, 1, 0]])
        images[view + 1] = np.clip(cv2.warpAffine(base, warp, SHAPE[::-1], flags=cv2.INTER_CUBIC), 0, 255).astype(
            np.uint8
        )
        truth[view + 1] = grid - [dx, 0]
        noisy = truth[view + 1] + rng.normal(0, noise_px, grid.shape)
        image = pycolmap.Image(name=f"{view:08d}.png", keypoints=noisy, camera_id=1, image_id=view + 1)
        # camera at x = dx / f (depth 1): the plane moves by -dx pixels
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(), [-dx / f, 0, 0]))
    for j, xyz in enumerate(world):
        track = pycolmap.Track()
        for image_id in images:
            track.add_element(image_id, j)
        rec.add_point3D(xyz, track)
    return rec, images, truth


def _relative_error(rec, truth):
    """RMS error of views 1 and 3's keypoints (still in a track) relative to view 2's, the reference, pixels."""
    reference = np.array([p.xy for p in rec.images[2].points2D]) - truth[2]
    errors = []
    for i in (1, 3):
        kept = np.array([p.has_point3D() for p in rec.images[i].points2D])
        errors.append((np.array([p.xy for p in rec.images[i].points2D]) - truth[i] - reference)[kept])
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))


def test_refine_tracks_makes_noisy_keypoints_consistent_with_the_reference_observation():
    from photonpano.plugins.pose._colmap import refine_tracks

    rec, images, truth = _scene(shift=7.3, noise_px=0.8)
    before = _relative_error(rec, truth)
    stats = refine_tracks(rec, images, window=21, max_shift_px=3.0)
    after = _relative_error(rec, truth)
    assert before > 0.9  # two independent 0.8 px errors
    assert after < 0.1, (before, after)
    assert stats["deleted"] <= 6 and 0.5 < stats["moved_px"] < 2.0  # of 120 observations


def test_refine_tracks_drops_observations_that_move_too_far():
    from photonpano.plugins.pose._colmap import refine_tracks

    rec, images, truth = _scene(shift=7.3, noise_px=0.0)
    wrong = rec.images[3].points2D[5]
    wrong.xy = wrong.xy + [2.5, 0]  # 2.5 px from the truth: found, but beyond max_shift_px
    stats = refine_tracks(rec, images, window=21, max_shift_px=1.0)
    assert stats["deleted"] == 1
    assert not rec.images[3].points2D[5].has_point3D()
    assert rec.num_points3D() == len(truth[1])  # a track of three keeps its other two


def test_prune_observations_deletes_the_outlier_only():
    from photonpano.plugins.pose._colmap import prune_observations

    rec, _, _ = _scene(shift=5.0, noise_px=0.05)
    outlier = rec.images[1].points2D[7]
    outlier.xy = outlier.xy + [0, 3.0]
    stats = prune_observations(rec, factor=5.0)
    assert stats["pruned"] == 1 and not rec.images[1].points2D[7].has_point3D()
    assert 0.1 < stats["threshold_px"] < 0.6
