"""Single Photon Challenge colour cubes: ``spc-challenge``.

Cubes are written as the challenge's FAQ reads them: ``np.packbits(frames, axis=2)`` of
(T, H, W, 3) 0/1 frames, saved with ``np.save``; read back and compared bit for bit.
"""

import numpy as np
import pytest
from photonpano.errors import SourceError
from photonpano.host import PluginHost
from photonpano.plugins.sources.spc_challenge import SpcChallengeConfig


def _colour_frames(t, h, w, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.random((t, h, w, 3)) < np.array([0.1, 0.3, 0.2])).astype(np.uint8)


def _sums(frames, edges):
    return np.stack([frames[a:b].sum(0) for a, b in zip(edges[:-1], edges[1:])])


def test_cubes_read_back_per_channel_and_as_any_channel(tmp_path):
    frames = _colour_frames(50, 24, 32, seed=1)
    scene = tmp_path / "attic"
    scene.mkdir()
    np.save(scene / "000000.npy", np.packbits(frames[:30], axis=2))
    np.save(scene / "000001.npy", np.packbits(frames[30:], axis=2))
    (scene / "000000.png").write_bytes(b"")  # a ground-truth image beside the first cube
    # the layout by hand: pixel (y, x) of channel c is bit 7 - x % 8 of byte [t, y, x // 8, c]
    cube = np.load(scene / "000000.npy")
    assert cube.shape == (30, 24, 4, 3) and (cube[4, 5, 2, 1] >> (7 - 19 % 8)) & 1 == frames[4, 5, 19, 1]
    edges = np.array([0, 3, 29, 31, 50])  # crosses the cube boundary
    for channels, want in (("any", frames.max(axis=-1)), ("red", frames[..., 0]), ("green", frames[..., 1]),
                           ("blue", frames[..., 2])):
        src = SpcChallengeConfig(path=scene, channels=channels, chunk_mb=0.01).build()
        assert (src.n_frames, src.height, src.width) == (50, 24, 32)
        np.testing.assert_array_equal(src.sum_ranges(edges), _sums(want, edges))
        np.testing.assert_array_equal(np.unpackbits(src.read_frames(28, 33), axis=-1), want[28:33])
    assert src.describe()["references"] == [str(scene / "000000.png"), None]
    sub = SpcChallengeConfig(path=[scene / "000001.npy"], start=4, stop=12).build()
    np.testing.assert_array_equal(sub.sum_ranges(np.array([0, 8])), _sums(frames[34:42].max(-1), [0, 8]))
    host = PluginHost()
    assert host.hook.photonpano_source_for_input(path=scene) == {"plugin": "spc-challenge", "path": str(scene)}
    assert host.hook.photonpano_source_for_input(path=scene / "000001.npy")["plugin"] == "spc-challenge"
    np.save(tmp_path / "mono.npy", np.packbits(frames[..., 0], axis=-1))
    assert host.hook.photonpano_source_for_input(path=tmp_path / "mono.npy")["plugin"] == "npy-cube"


def test_any_channel_is_a_binary_frame_of_the_summed_flux():
    """OR of independent Bernoulli channels: P(1) = 1 - exp(-(phi_R + phi_G + phi_B))."""
    rng = np.random.default_rng(2)
    phi = np.array([0.05, 0.2, 0.1])
    bits = rng.random((200_000, 3)) < 1 - np.exp(-phi)
    assert bits.any(axis=1).mean() == pytest.approx(1 - np.exp(-phi.sum()), abs=3e-3)


def test_bad_cubes_are_one_line_errors_naming_the_file(tmp_path):
    frames = _colour_frames(10, 16, 16)
    np.save(tmp_path / "ok.npy", np.packbits(frames, axis=2))
    raw = (tmp_path / "ok.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(raw[:-100])
    with pytest.raises(SourceError, match=r"cut\.npy is truncated: its header declares \(10, 16, 2, 3\) uint8 = 960 "
                                          r"bytes of data, the file holds 860") as err:
        SpcChallengeConfig(path=tmp_path / "cut.npy").build()
    assert "\n" not in str(err.value)
    np.save(tmp_path / "mono.npy", np.packbits(frames[..., 0], axis=-1))
    with pytest.raises(SourceError, match=r"mono\.npy holds \(10, 16, 2\) uint8; expected a Single Photon Challenge "
                                          r"cube \(T, H, W/8, 3\) uint8, e\.g\. \(1024, 800, 100, 3\)"):
        SpcChallengeConfig(path=tmp_path / "mono.npy").build()
    np.save(tmp_path / "wide.npy", np.packbits(_colour_frames(4, 16, 24), axis=2))
    with pytest.raises(SourceError, match=r"wide\.npy holds frames of \(16, 3, 3\) \(H, W/8, C\); expected "
                                          r"\(16, 2, 3\) like ok\.npy"):
        SpcChallengeConfig(path=[tmp_path / "ok.npy", tmp_path / "wide.npy"]).build()
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match=r"no \.npy cubes in .*empty"):
        SpcChallengeConfig(path=tmp_path / "empty").build()
