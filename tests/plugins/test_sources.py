import hashlib

import numpy as np
import pytest
from photonpano.errors import SourceError
from photonpano.plugins.sources.npy_cube import NpyCubeConfig
from photonpano.plugins.sources.simulate import SimulateConfig, camera_path
from testdata import packed_cube


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_simulated_capture_matches_its_ground_truth_flux(tiny_capture):
    # Mean detections of the first 200 frames agree with 1 - exp(-flux * I) of the true path.
    import cv2

    cap = tiny_capture
    counts = cap.sum_ranges(np.array([0, 200]))[0] / 200
    intensity = cv2.warpPerspective(cap.scene_flux * cap.exposure_s, cap.ground_truth[100], (cap.width, cap.height),
                                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    expected = 1 - np.exp(-intensity)
    assert abs(counts.mean() - expected.mean()) < 0.01
    assert np.corrcoef(counts.ravel(), expected.ravel())[0, 1] > 0.9


def test_camera_path_starts_centred_and_refuses_to_leave_the_scene():
    cfg = SimulateConfig(frames=1000, speed_px_per_frame=0.0, vibration_px=0.0)
    h = camera_path(cfg, (576, 1440))
    centre = h[0] @ [(cfg.width - 1) / 2, (cfg.height - 1) / 2, 1]
    np.testing.assert_allclose(centre[:2], [719.5, 287.5])
    with pytest.raises(SourceError, match="leaves the 1440x576 scene"):
        camera_path(SimulateConfig(frames=100_000, speed_px_per_frame=0.05), (576, 1440))


@pytest.mark.parametrize("layout", ["packed", "unpacked-uint8", "unpacked-bool"])
def test_npy_cube_reads_every_layout_identically(tmp_path, tiny_capture, layout):
    packed = packed_cube(tiny_capture)[:600]
    frames = np.unpackbits(packed, axis=-1)
    data = {"packed": packed, "unpacked-uint8": frames, "unpacked-bool": frames.astype(bool)}[layout]
    path = tmp_path / "cube.npy"
    np.save(path, data)
    before = _digest(path)
    cube = NpyCubeConfig(path=path, start=100, stop=500).build()
    assert (cube.n_frames, cube.height, cube.width) == (400, 128, 248)
    assert cube.packed == (layout == "packed")
    edges = np.array([0, 7, 300, 400])
    want = np.stack([frames[100 + a:100 + b].sum(0) for a, b in zip(edges[:-1], edges[1:])])
    np.testing.assert_array_equal(cube.sum_ranges(edges), want)
    assert _digest(path) == before  # the input is never written


def test_npy_cube_errors_name_the_file(tmp_path):
    with pytest.raises(SourceError, match="does not exist"):
        NpyCubeConfig(path=tmp_path / "missing.npy").build()
    bad = tmp_path / "float.npy"
    np.save(bad, np.zeros((4, 8, 8), np.float32))
    with pytest.raises(SourceError, match=r"float\.npy has dtype float32; expected uint8"):
        NpyCubeConfig(path=bad).build()
    flat = tmp_path / "flat.npy"
    np.save(flat, np.zeros((4, 8), np.uint8))
    with pytest.raises(SourceError, match=r"flat\.npy has shape \(4, 8\)"):
        NpyCubeConfig(path=flat).build()
    junk = tmp_path / "junk.npy"
    junk.write_bytes(b"not a numpy file")
    with pytest.raises(SourceError, match="not a readable .npy"):
        NpyCubeConfig(path=junk).build()
    ok = tmp_path / "ok.npy"
    np.save(ok, np.zeros((10, 8, 2), np.uint8))
    with pytest.raises(SourceError, match="outside"):
        NpyCubeConfig(path=ok, stop=11).build()


def test_simulate_writes_a_cube_and_never_overwrites(tmp_path):
    path = tmp_path / "sim.npy"
    cfg = SimulateConfig(frames=50, height=16, width=32, cube_path=path, speed_px_per_frame=0, vibration_px=0)
    cap = cfg.build()
    np.testing.assert_array_equal(np.load(path), cap.cube)
    with pytest.raises(SourceError, match="refusing to overwrite"):
        cfg.build()
