"""Short clips: fewer levels with a one-line note, or one clear error when nothing can be registered.

The clips are written here (an image folder panning 3 px per frame across smoothed
noise), plus the repository's real 4-frame Photron clip ``tests/data/highspeed/beam.mraw``.
"""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import photonpano
import pytest
from photonpano.errors import StageError

BEAM = Path(__file__).parent / "data" / "highspeed" / "beam.mraw"


def _clip(folder: Path, frames: int) -> Path:
    """``frames`` 160x300 8-bit PNGs of a textured scene panning 3 px per frame."""
    rng = np.random.default_rng(0)
    scene = cv2.GaussianBlur((rng.random((200, 400)) * 255).astype(np.uint8), (0, 0), 2)
    scene = cv2.normalize(scene, None, 0, 255, cv2.NORM_MINMAX)
    folder.mkdir()
    for t in range(frames):
        assert cv2.imwrite(str(folder / f"{t:03d}.png"), scene[20:180, 10 + 3 * t:310 + 3 * t])
    return folder


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "photonpano.cli", "-q", *map(str, args)], capture_output=True,
                          text=True, timeout=300)


def test_a_short_clip_runs_fewer_levels_with_a_note(tmp_path):
    clip = _clip(tmp_path / "frames", 6)
    result = photonpano.run({"source": {"plugin": "video", "path": str(clip), "frame_rate_hz": 1000},
                             "merger": "mean", "levels": 3, "level_schemes": ["pairwise"]}, progress=False)
    assert result.summary["group_size"]["group_size"] == 2
    assert [row["level"] for row in result.summary["levels"]] == [1, 2]
    assert result.summary["notes"] == [
        "a capture of 6 frames in groups of 2 has room for 2 of the 3 levels; running 2 (groups of 2 frames allow "
        "at most 2 levels: level 3's would be centred 0.5 frames apart)"]
    # the pan is recovered: frame t is the scene from x = 10 + 3 t
    np.testing.assert_allclose(np.diff(result.homographies[:, 0, 2]), 3.0, atol=0.1)


def test_cli_prints_the_note_as_one_line(tmp_path):
    clip = _clip(tmp_path / "frames", 4)
    result = _cli("pano", clip, "-o", tmp_path / "out", "--set", "source.frame_rate_hz=1000", "--set", "levels=3")
    assert result.returncode == 0, result.stderr
    notes = [line for line in result.stderr.splitlines() if line.startswith("note: ")]
    assert notes == ["note: a capture of 4 frames in groups of 2 has room for 2 of the 3 levels; running 2 (groups "
                     "of 2 frames allow at most 2 levels: level 3's would be centred 0.5 frames apart)"]
    summary = json.loads((tmp_path / "out" / "run.json").read_text())
    assert len(summary["levels"]) == 2 and summary["notes"] == [notes[0][len("note: "):]]


def test_a_clip_that_fits_its_levels_has_no_note(tmp_path):
    clip = _clip(tmp_path / "frames", 8)
    result = photonpano.run({"source": {"plugin": "video", "path": str(clip), "frame_rate_hz": 1000},
                             "merger": "mean", "levels": 2, "level_schemes": ["pairwise"]}, progress=False)
    assert result.summary["notes"] == [] and len(result.summary["levels"]) == 2


@pytest.mark.parametrize("frames", [1, 3])
def test_a_clip_too_short_to_register_is_one_clear_error(tmp_path, frames):
    clip = _clip(tmp_path / "frames", frames)
    with pytest.raises(StageError, match=f"a capture of {frames} frames? is too short to register: at least 4 are "
                                         "needed"):
        photonpano.run({"source": {"plugin": "video", "path": str(clip), "frame_rate_hz": 1000}}, progress=False)
    result = _cli("pano", clip, "-o", tmp_path / "out", "--set", "source.frame_rate_hz=1000")
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [
        f"error: resampler (MidpointResampler): a capture of {frames} frame{'s' if frames > 1 else ''} is too short "
        "to register: at least 4 are needed (2 groups of at least 2 frames)"]


def test_the_real_four_frame_beam_clip_reconstructs(tmp_path):
    # `photonpano pano beam.mraw` failed: "Groups: reference frames must be strictly increasing"
    result = _cli("pano", BEAM, "-o", tmp_path / "out")
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "out" / "run.json").read_text())
    assert [row["level"] for row in summary["levels"]] == [1, 2]
    assert summary["levels"][1]["groups"] == 4
    assert summary["status"] == "ok"
