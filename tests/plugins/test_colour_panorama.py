"""Colour filter array handling: filtered pixels missing for registration, a colour panorama."""

from types import SimpleNamespace

import numpy as np
import pytest
from capture_helpers import embed_colorspad
from photonpano.compose import Panorama
from photonpano.plugins.compositors.drizzle import DrizzleConfig
from photonpano.plugins.observers.colour_panorama import colour_panorama, photonpano_panorama_finished
from photonpano.plugins.sources._swissspad_sensor import bundled_sensor_file, load_cfa
from photonpano.plugins.sources.npy_cube import NpyCubeConfig

P_WHITE, P_RGB = 0.4, (0.1, 0.2, 0.05)  # detection probability per frame behind each filter


@pytest.fixture(scope="module")
def colour_cube(tmp_path_factory):
    """400 raw frames of a uniform scene seen through the real colour filter layout."""
    cfa = load_cfa(bundled_sensor_file("cfa"), (254, 496))
    p = np.full(cfa.shape, P_WHITE)
    for c, pc in enumerate(P_RGB):
        p[cfa == c] = pc
    frames = (np.random.default_rng(0).random((400, 254, 496)) < p).astype(np.uint8)
    path = tmp_path_factory.mktemp("colour") / "raw.npy"
    np.save(path, embed_colorspad(np.packbits(frames, axis=-1)))
    return path, cfa


def test_filtered_pixels_are_inpainted_from_unfiltered_neighbours(colour_cube):
    path, cfa = colour_cube
    plain = NpyCubeConfig(path=path, fix="colorspad").build().sum_ranges(np.array([0, 400]))[0] / 400
    fixed = NpyCubeConfig(path=path, fix="colorspad", cfa="colorspad").build().sum_ranges(np.array([0, 400]))[0] / 400
    for c, pc in enumerate(P_RGB):
        assert abs(plain[cfa == c].mean() - pc) < 0.01
        assert abs(fixed[cfa == c].mean() - P_WHITE) < 0.01  # looks like its unfiltered neighbours now
    np.testing.assert_array_equal(fixed[cfa < 0], plain[cfa < 0])


def test_colour_panorama_recovers_each_channel(colour_cube, tmp_path):
    path, cfa = colour_cube
    cfg = NpyCubeConfig(path=path, fix="colorspad", cfa="colorspad", colour_panorama=True)
    source = cfg.build()
    homographies = np.repeat(np.eye(3)[None], 400, axis=0)
    rgb = colour_panorama(source, homographies, (254, 496))
    assert rgb.shape == (254, 496, 3) and rgb.dtype == np.float32
    for c, pc in enumerate(P_RGB):
        seen = rgb[..., c][np.isfinite(rgb[..., c])]
        assert seen.size > 0.9 * (cfa == c).sum()  # a static camera sees each channel at its own pixels only
        want = -np.log1p(-pc) * 100_000  # photons/s at 100 kHz
        assert abs(np.median(seen) / want - 1) < 0.05
    # the observer writes the outputs when the spec asks for them, through the spec's compositor
    spec = SimpleNamespace(source=cfg, panorama_subbatch_px=0.25, compositor=DrizzleConfig())
    pano = Panorama(flux=np.zeros((254, 496), np.float32), frames=np.zeros((254, 496), np.float32),
                    homographies=homographies)
    photonpano_panorama_finished(panorama=pano, spec=spec, source=source, out_dir=tmp_path)
    # a static camera: drizzle drops each pixel onto its own canvas pixel, as the bilinear warp does
    np.testing.assert_allclose(np.load(tmp_path / "panorama_rgb.npy"), rgb, rtol=1e-5)
    from photonpano.hdr import read_flux_tiff
    tif, valid = read_flux_tiff(tmp_path / "panorama_rgb.tif")
    assert np.array_equal(tif, np.load(tmp_path / "panorama_rgb.npy"), equal_nan=True)
    assert np.array_equal(valid, np.isfinite(tif).all(axis=-1))
    import cv2

    png = cv2.imread(str(tmp_path / "panorama_rgb.png"), cv2.IMREAD_UNCHANGED)
    assert png.shape == (254, 496, 3) and png.dtype == np.uint16
    with pytest.raises(ValueError, match="no colour filter layout"):
        colour_panorama(NpyCubeConfig(path=path, fix="colorspad").build(), homographies, (254, 496))


def test_panorama_stage_composites_colour_in_the_same_pass(colour_cube):
    path, _ = colour_cube
    cfg = NpyCubeConfig(path=path, fix="colorspad", cfa="colorspad", colour_panorama=True)
    source = cfg.build()
    homographies = np.repeat(np.eye(3)[None], 400, axis=0)
    from photonpano.compose import compose
    from photonpano.plugins.compositors.colour import ColourPanorama

    make = DrizzleConfig().build
    stage = cfg.panorama_compositor(make)
    assert isinstance(stage, ColourPanorama)
    assert not isinstance(NpyCubeConfig(path=path, fix="colorspad", cfa="colorspad").panorama_compositor(make),
                          ColourPanorama)
    pano = compose(source, homographies, stage, canvas_shape=(254, 496))
    plain = compose(source, homographies, make(), canvas_shape=(254, 496))
    np.testing.assert_array_equal(pano.flux, plain.flux)  # the panorama is the one without colour
    np.testing.assert_allclose(pano.colour, colour_panorama(source, homographies, (254, 496), make=make), rtol=1e-5)


def test_the_colour_panorama_leaves_a_moving_disc_out_as_the_robust_merge_does():
    """A disc crossing a colour capture leaves a ghost in every plane unless the colour is robust too (issue 28).

    4 000 frames of the office through the real filter layout (96 x 160 px, flux 1), a disc
    of radius 12 px at 0.15 px/frame, composited with the true motion by the panorama
    stage's colour compositor around ``drizzle``: plain 26.7 dB (mean over R, G, B), robust
    30.3 dB, the static capture 30.4 dB; on the static capture robust and plain differ by
    0.030 dB (before the wide, edge-aware colour ratio: 26.2, 29.2 and 29.3 dB,
    0.026 dB).
    """
    import cv2
    from photonpano.compose import canvas_homographies, compose
    from photonpano.metrics import colour_scene_on_canvas, psnr
    from photonpano.plugins.compositors.colour import ColourPanorama
    from photonpano.plugins.sources.simulate import SimulateConfig

    settings = {"cfa": "colorspad", "frames": 4000, "height": 96, "width": 160, "scene_width": 480, "flux": 1.0,
                "speed_px_per_frame": 0.03}
    captures = {"static": SimulateConfig(**settings).build(),
                "disc": SimulateConfig(**settings, mover_radius_px=12, mover_speed_px_per_frame=0.15).build()}
    static = captures["static"]
    to_canvas, shape = canvas_homographies(static.ground_truth, static.width, static.height, 1.0)
    from_scene = to_canvas[0] @ np.linalg.inv(static.ground_truth[0])
    scene = colour_scene_on_canvas(static, from_scene, shape)
    panos = {(name, robust): compose(capture, to_canvas, ColourPanorama(DrizzleConfig(robust=robust).build),
                                     canvas_shape=shape).colour
             for name, capture in captures.items() for robust in (False, True)}
    seen = np.logical_and.reduce([np.isfinite(p).all(-1) for p in (scene, *panos.values())])
    mask = cv2.erode(seen.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    db = {key: np.mean([psnr(p[..., c], scene[..., c], mask) for c in range(3)]) for key, p in panos.items()}
    assert abs(db["static", True] - db["static", False]) < 0.05, db
    assert db["disc", False] < db["static", False] - 2.0, db  # the ghost
    assert db["disc", True] > db["static", False] - 0.3, db
