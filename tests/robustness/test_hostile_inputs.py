"""Hostile captures: lying headers, truncated files, wrong types; one line, nothing written, input intact."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import numpy as np
import pytest
from robust import assert_one_line_error, digests, invoke

DATA = Path(__file__).parent.parent / "data" / "highspeed"


def _npy_with_header(path: Path, shape: tuple, descr: str = "|u1", data: bytes = b"") -> Path:
    """An .npy file whose header declares ``shape`` followed by ``data`` (not necessarily that much)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    path.write_bytes(buf.getvalue() + data)
    return path


def _cube(path: Path, frames: int = 50, shape: tuple = (32, 8), dtype=np.uint8, order: str = "C") -> Path:
    data = np.random.default_rng(1).integers(0, 256, (frames, *shape)).astype(dtype)
    np.save(path, np.asfortranarray(data) if order == "F" else data)
    return path


def _truncate(path: Path, keep: float = 0.5) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    return path


def _raw_half_cube(path: Path) -> Path:
    return _cube(path, frames=40, shape=(256, 64))


def _make(name: str, tmp: Path) -> tuple[Path, list[str], list[str]]:
    """Return (input, extra --set arguments, expected message pieces) of case ``name``."""
    if name == "negative dimension":
        return _npy_with_header(tmp / "neg.npy", (-5, 32, 8)), [], ["neg.npy", "negative dimension"]
    if name == "header claims 10^12 frames":
        return (_npy_with_header(tmp / "huge.npy", (10**12, 32, 8), data=bytes(256)), [],
                ["huge.npy", "truncated", "1000000000000"])
    if name == "truncated cube":
        return _truncate(_cube(tmp / "cut.npy")), [], ["cut.npy", "truncated"]
    if name == "object array (pickle)":
        path = tmp / "obj.npy"
        np.save(path, np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
        return path, [], ["obj.npy", "Python objects"]
    if name == "random bytes":
        (tmp / "noise.npy").write_bytes(np.random.default_rng(2).bytes(5000))
        return tmp / "noise.npy", [], ["noise.npy", "not a readable .npy file"]
    if name == "empty file":
        (tmp / "empty.npy").write_bytes(b"")
        return tmp / "empty.npy", [], ["empty.npy", "not a readable .npy file"]
    if name == "bad header text":
        (tmp / "hdr.npy").write_bytes(np.lib.format.magic(1, 0) + b"\x10\x00{'descr': os.system('x')}\n")
        return tmp / "hdr.npy", [], ["hdr.npy", "not a readable .npy file"]
    if name == "2-D array":
        np.save(tmp / "flat.npy", np.zeros((32, 8), np.uint8))
        return tmp / "flat.npy", [], ["flat.npy", "expected a photon cube"]
    if name == "float cube":
        return _cube(tmp / "float.npy", dtype=np.float32), [], ["float.npy", "float32"]
    if name == "no frames":
        np.save(tmp / "none.npy", np.zeros((0, 32, 8), np.uint8))
        return tmp / "none.npy", [], ["none.npy", "holds 0 frames"]
    if name == "fortran order":
        return _cube(tmp / "fortran.npy", order="F"), [], ["fortran.npy", "Fortran order"]
    if name == "start beyond the end":
        return _cube(tmp / "short.npy"), ["source.start=100000"], ["short.npy", "outside"]
    if name == "inpaint mask claims 10^12 frames":
        mask = _npy_with_header(tmp / "mask.npy", (10**12, 254, 496), descr="|b1", data=bytes(1000))
        return (_raw_half_cube(tmp / "raw.npy"), ["source.fix=grayspad", f"source.inpaint_mask={mask}"],
                ["mask.npy", "inpaint_mask", "truncated"])
    if name == "inpaint mask negative dimension":
        mask = _npy_with_header(tmp / "mask.npy", (254, -496), descr="|b1")
        return (_raw_half_cube(tmp / "raw.npy"), ["source.fix=grayspad", f"source.inpaint_mask={mask}"],
                ["mask.npy", "negative dimension"])
    if name == "inpaint mask too small":
        mask = tmp / "mask.npy"
        np.save(mask, np.zeros((10, 10), bool))
        return (_raw_half_cube(tmp / "raw.npy"), ["source.fix=grayspad", f"source.inpaint_mask={mask}"],
                ["mask.npy", "expected at least"])
    if name in ("cihx width 0", "cihx height 0"):
        tag = b"<width>1024</width>" if "width" in name else b"<height>80</height>"
        zero = b"<width>0</width>" if "width" in name else b"<height>0</height>"
        (tmp / "beam.cihx").write_bytes((DATA / "beam.cihx").read_bytes().replace(tag, zero))
        shutil.copy(DATA / "beam.mraw", tmp / "beam.mraw")
        return tmp / "beam.mraw", [], ["beam.cihx", "positive sizes"]
    if name == "truncated mraw":
        shutil.copy(DATA / "beam.cihx", tmp / "beam.cihx")
        shutil.copy(DATA / "beam.mraw", tmp / "beam.mraw")
        return _truncate(tmp / "beam.mraw"), [], ["beam.mraw", "truncated"]
    if name == "mraw without header":
        shutil.copy(DATA / "beam.mraw", tmp / "lone.mraw")
        return tmp / "lone.mraw", [], ["lone.mraw", "no header"]
    if name == "truncated video, strict":
        return _truncated_avi(tmp), ["source.strict=true", "source.frame_rate_hz=1000"], \
            ["clip.avi", "announces 60 frames", "strict"]
    if name == "missing input":
        return tmp / "missing.npy", [], ["missing.npy", "does not exist"]
    if name == "unknown file type":
        (tmp / "notes.txt").write_text("hello")
        return tmp / "notes.txt", [], ["notes.txt", "no source plugin reads"]
    if name == "empty folder":
        (tmp / "empty_dir").mkdir()
        return tmp / "empty_dir", [], ["empty_dir", "no source plugin reads"]
    raise KeyError(name)


def _truncated_avi(tmp: Path, frames: int = 60) -> Path:
    av = pytest.importorskip("av")
    path = tmp / "clip.avi"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mjpeg", rate=30)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuvj420p"
        for i in range(frames):
            image = np.full((48, 64, 3), 4 * i, np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return _truncate(path)


CASES = ["negative dimension", "header claims 10^12 frames", "truncated cube", "object array (pickle)",
         "random bytes", "empty file", "bad header text", "2-D array", "float cube", "no frames",
         "fortran order", "start beyond the end", "inpaint mask claims 10^12 frames",
         "inpaint mask negative dimension", "inpaint mask too small", "cihx width 0", "cihx height 0",
         "truncated mraw", "mraw without header", "truncated video, strict", "missing input",
         "unknown file type", "empty folder"]


@pytest.mark.parametrize("name", CASES)
def test_hostile_input_is_one_line_and_writes_nothing(tmp_path, name):
    inputs = tmp_path / "in"
    inputs.mkdir()
    path, overrides, pieces = _make(name, inputs)
    before = digests(inputs)
    out = tmp_path / "out"
    args = ["pano", path, "-o", out]
    for item in overrides:
        args += ["--set", item]
    assert_one_line_error(invoke(*args), *pieces)
    assert digests(inputs) == before  # inputs unchanged
    assert not out.exists()  # nothing written before the source is open


def test_packed_cube_with_dark_first_frames_is_detected_packed(tmp_path):
    from photonpano.plugins.sources.npy_cube import NpyCubeConfig

    frames = np.random.default_rng(0).random((600, 32, 64)) < 0.3
    frames[:300] = False  # the first 300 frames are dark (lens cap, shutter)
    np.save(tmp_path / "dark.npy", np.packbits(frames, axis=-1))
    source = NpyCubeConfig(path=tmp_path / "dark.npy").build()
    assert source.packed and source.width == 64
    counts = source.sum_ranges(np.array([300, 600]))
    assert counts.sum() == frames[300:].sum()  # the photons read back exactly


def test_all_dark_cube_uses_the_sensor_width(tmp_path):
    from photonpano.plugins.sources.npy_cube import NpyCubeConfig

    np.save(tmp_path / "cap.npy", np.zeros((20, 256, 64), np.uint8))  # SwissSPAD2 half array, lens cap on
    assert NpyCubeConfig(path=tmp_path / "cap.npy", fix="grayspad").build().packed
    assert not NpyCubeConfig(path=tmp_path / "cap.npy").build().packed  # no sensor: bytes 0/1 read unpacked


def test_truncated_video_is_announced(tmp_path):
    from photonpano.plugins.sources.video import VideoConfig

    path = _truncated_avi(tmp_path)
    with pytest.warns(UserWarning, match="announces 60 frames"):
        source = VideoConfig(path=path, frame_rate_hz=1000).build()
    assert 0 < source.n_frames < 60
    assert "announces 60 frames" in source.describe()["warnings"][0]
