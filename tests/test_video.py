"""`photonpano video`: a finished run rendered as H.264, decoded back and measured."""

from __future__ import annotations

import cv2
import numpy as np
import photonpano
import pytest
from photonpano.cli import app
from photonpano.video import render_video, to_codes, white_point
from typer.testing import CliRunner

av = pytest.importorskip("av")
runner = CliRunner()

SPEC = {"source": {"plugin": "simulate", "frames": 2400, "height": 128, "width": 248, "vibration_px": 2.0},
        "group_size": 300, "levels": 2, "outputs": {"merged_frames": True}}


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("video") / "run"
    photonpano.run(SPEC, out_dir=out, progress=False)
    return out


def _decode(path):
    with av.open(str(path)) as container:
        return np.stack([frame.to_ndarray(format="gray") for frame in container.decode(video=0)])


def _common_rectangle(frames, margin=4):
    """Rows and columns of a rectangle that every frame observed (non-black), shrunk by ``margin``."""
    seen = (frames > 0).all(axis=0)
    rows = np.flatnonzero(seen.mean(axis=1) > 0.5)
    cols = np.flatnonzero(seen[rows].all(axis=0))
    rows = np.flatnonzero(seen[:, cols].all(axis=1))
    return slice(rows.min() + margin, rows.max() + 1 - margin), slice(cols.min() + margin, cols.max() + 1 - margin)


def _shifts(frames, region):
    """Frame-to-frame shifts (px) of ``region`` by phase correlation."""
    crops = [np.float32(f[region]) for f in frames]
    window = cv2.createHanningWindow(crops[0].shape[::-1], cv2.CV_32F)
    return np.array([np.hypot(*cv2.phaseCorrelate(a, b, window)[0]) for a, b in zip(crops, crops[1:])])


def test_stabilised_video_holds_the_scene_still(run_folder, tmp_path):
    out = tmp_path / "stable.mp4"
    result = runner.invoke(app, ["video", str(run_folder), "-o", str(out), "--exposure", "200", "--frames", "10",
                                 "--fps", "24"])
    assert result.exit_code == 0, result.output
    frames = _decode(out)
    pano = np.load(run_folder / "panorama.npy")
    # the requested frame count, the canvas size (padded to even), the requested rate
    assert frames.shape == (10, pano.shape[0] + pano.shape[0] % 2, pano.shape[1] + pano.shape[1] % 2)
    with av.open(str(out)) as container:
        assert container.streams.video[0].average_rate == 24
        assert container.streams.video[0].codec_context.name == "h264"
    rows, cols = _common_rectangle(frames)
    assert rows.stop - rows.start > 60 and cols.stop - cols.start > 100  # a real region, not a sliver
    shifts = _shifts(frames, (rows, cols))
    assert shifts.max() < 0.5, shifts
    # the measurement sees motion where there is some: the same exposures seen by the camera (flythrough)
    # move by the pan, about 0.02 px/frame x 244 frames between video frames
    moving = tmp_path / "fly.mp4"
    assert runner.invoke(app, ["video", str(run_folder), "-o", str(moving), "--mode", "flythrough",
                               "--frames", "10"]).exit_code == 0
    fly = _decode(moving)
    assert fly.shape == (10, 128, 248)
    assert np.median(_shifts(fly, (slice(16, 112), slice(16, 232)))) > 2.0


def test_flythrough_views_match_the_panorama(run_folder, tmp_path):
    """Each flythrough frame is the panorama resampled at the frame's pose: compare with a direct warp."""
    out = tmp_path / "fly.mp4"
    info = render_video(run_folder, out, mode="flythrough", frames=3, width=124)
    assert (info.frames, info.width, info.height) == (3, 124, 64)
    frames = _decode(out)
    assert frames.shape == (3, 64, 124)
    run = photonpano.load(run_folder)
    t = 2399 // 2  # the middle of three evenly spaced views
    direct = cv2.warpPerspective(np.nan_to_num(run.panorama), run.homographies[t], (248, 128),
                                 flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    expected = cv2.resize(to_codes(direct, white_point(run.panorama)), (124, 64), interpolation=cv2.INTER_AREA)
    inner = (slice(4, 60), slice(4, 120))
    assert np.abs(frames[1][inner].astype(float) - expected[inner]).mean() < 3.0  # codec error, in 8-bit codes


def test_levels_video_shows_every_merged_frame(run_folder, tmp_path):
    out = tmp_path / "levels.mp4"
    info = render_video(run_folder, out, mode="levels")
    groups = sum(len(np.load(p)) for p in run_folder.glob("level_*/references.npy"))
    assert info.frames == groups == len(_decode(out))
    # each merged frame lands where the panorama is: the mean absolute difference in codes is small
    frames = _decode(out).astype(float)
    pano = np.load(run_folder / "panorama.npy")
    codes = to_codes(pano, white_point(pano)).astype(float)
    last = frames[-1][:pano.shape[0], :pano.shape[1]]
    seen = last > 0
    seen[:40, :160] = False  # the level label
    assert seen.mean() > 0.3 and np.abs(last - codes)[seen].mean() < 12


def test_video_errors_are_one_line(run_folder, tmp_path):
    existing = tmp_path / "taken.mp4"
    existing.write_bytes(b"user data")
    cases = [([str(tmp_path / "nothing"), "-o", str(tmp_path / "a.mp4")], "is not a folder"),
             ([str(tmp_path), "-o", str(tmp_path / "a.mp4")], "no run.json"),
             ([str(run_folder), "-o", str(existing)], "exists; pass --force"),
             ([str(run_folder), "-o", str(tmp_path / "a.avi")], "expected a .mp4"),
             ([str(run_folder), "-o", str(tmp_path / "a.mp4"), "--mode", "spin"], "--mode must be one of"),
             ([str(run_folder), "-o", str(tmp_path / "a.mp4"), "--exposure", "999999"], "--exposure must be")]
    for args, message in cases:
        result = runner.invoke(app, ["video", *args])
        assert result.exit_code == 1 and message in result.output, (args, result.output)
        assert "Traceback" not in result.output
    assert existing.read_bytes() == b"user data"  # never overwritten without --force
    assert not (tmp_path / "a.mp4").exists()


def test_video_of_a_run_without_level_dumps_says_what_to_set(run_folder, tmp_path):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run_folder, out, ignore=shutil.ignore_patterns("level_*"))
    result = runner.invoke(app, ["video", str(out), "-o", str(tmp_path / "l.mp4"), "--mode", "levels"])
    assert result.exit_code == 1 and "merged_frames: true" in result.output
    (out / "homographies.npy").unlink()
    result = runner.invoke(app, ["video", str(out), "-o", str(tmp_path / "l.mp4")])
    assert result.exit_code == 1 and "no homographies.npy" in result.output


def test_spec_output_video_is_written_with_the_run(tmp_path):
    out = tmp_path / "run"
    spec = {**SPEC, "outputs": {"video": True, "report": False, "trajectory_plot": False}}
    photonpano.run(spec, out_dir=out, progress=False)
    frames = _decode(out / "video.mp4")
    assert len(frames) == 2400 // 300  # one per level-1 group's worth of frames, without overlap
    pano = np.load(out / "panorama.npy")
    assert frames.shape[1:] == (pano.shape[0] + pano.shape[0] % 2, pano.shape[1] + pano.shape[1] % 2)
    rows, cols = _common_rectangle(frames)
    assert _shifts(frames, (rows, cols)).max() < 0.5
    import json

    assert "video.mp4" in json.loads((out / "manifest.json").read_text())["files"]


def test_a_capture_that_cannot_be_reopened_is_one_line(run_folder, tmp_path):
    """A run whose capture is gone (a moved .npy cube) or truncated: one line naming the path."""
    import json
    import shutil

    cube = tmp_path / "cube.npy"
    np.save(cube, np.zeros((2400, 128, 31), np.uint8))  # packed frames, 248 pixels wide
    out = tmp_path / "run"
    shutil.copytree(run_folder, out)
    summary = json.loads((out / "run.json").read_text())
    summary["spec"]["source"] = {"plugin": "npy-cube", "path": str(cube)}
    (out / "run.json").write_text(json.dumps(summary))
    np.save(cube, np.zeros((1000, 128, 31), np.uint8))  # the capture changed since the run
    result = runner.invoke(app, ["video", str(out), "-o", str(tmp_path / "v.mp4")])
    assert result.exit_code == 1 and "1000 frames" in result.output and "2400" in result.output, result.output
    cube.unlink()
    result = runner.invoke(app, ["video", str(out), "-o", str(tmp_path / "v.mp4")])
    assert result.exit_code == 1 and str(cube) in result.output and "Traceback" not in result.output, result.output
    assert not (tmp_path / "v.mp4").exists()
    # the flythrough needs no capture
    assert runner.invoke(app, ["video", str(out), "-o", str(tmp_path / "v.mp4"), "--mode", "flythrough",
                               "--frames", "2"]).exit_code == 0


def test_without_pyav_the_error_names_the_extra(run_folder, tmp_path, monkeypatch):
    import sys

    from photonpano.errors import MissingDependency

    monkeypatch.setitem(sys.modules, "av", None)  # as if not installed
    result = runner.invoke(app, ["video", str(run_folder), "-o", str(tmp_path / "v.mp4")])
    assert result.exit_code == 1 and "photonpano[video]" in result.output and "Traceback" not in result.output
    with pytest.raises(MissingDependency, match=r"photonpano\[video\]"):  # before the run, not after it
        photonpano.run({**SPEC, "outputs": {"video": True}}, out_dir=tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()
