"""Feature caching: a merged frame is described once per content, across register_pairs calls."""

import numpy as np
import pytest
from photonpano.locator import LocatorContext
from photonpano.plugins.locators.opencv_ecc import OpenCVEccConfig
from photonpano.plugins.locators.opencv_features import OpenCVOrbConfig
from photonpano.plugins.locators.opencv_sift import OpenCVSiftConfig
from photonpano.testing import merged_frames, textured_image


@pytest.fixture(scope="module")
def four_frames():
    """Four overlapping 160x240 crops of the bundled photo (3 px apart), as merged frames."""
    base = textured_image(160, 260)
    return merged_frames([base[:, 3 * i:3 * i + 240] for i in range(4)])


CHAIN = np.array([[0, 1], [1, 2], [2, 3]])
EXTRA = np.array([[0, 2], [1, 3]])


def _eye(n):
    return np.repeat(np.eye(3)[None], n, axis=0)


@pytest.mark.parametrize("config", [OpenCVSiftConfig(image_scale=1.0), OpenCVOrbConfig(refine="lm")],
                         ids=lambda c: c.plugin)
def test_second_call_of_a_level_reuses_every_description(four_frames, config):
    locator = config.build()
    chain = locator.register_pairs(four_frames, CHAIN, _eye(3))
    # each distinct frame is described once per call
    assert locator.cache_stats()["features_misses"] == 4 and locator.cache_stats()["features_hits"] == 0
    locator.register_pairs(four_frames, EXTRA, _eye(2))  # the longer-offset pairs of the same level
    stats = locator.cache_stats()
    assert stats["features_misses"] == 4 and stats["features_hits"] == 4
    # cached results are the results: a fresh locator gives the same homographies
    fresh = config.build().register_pairs(four_frames, CHAIN, _eye(3))
    np.testing.assert_array_equal(chain.homographies, fresh.homographies)
    # translation of 3 px per frame: frame b's pixel x is frame a's x + 3
    np.testing.assert_allclose(chain.homographies[:, 0, 2], 3.0, atol=0.2)


def test_changed_frames_are_described_again_and_old_ones_evicted(four_frames):
    locator = OpenCVSiftConfig(refine="lm").build()
    locator.register_pairs(four_frames, CHAIN, _eye(3))
    locator.reset_cache_stats()
    changed = merged_frames([np.flip(f / 1e5, axis=1).astype(np.float32) for f in four_frames.flux])
    locator.register_pairs(changed, CHAIN, _eye(3))  # the next level: every frame re-merged
    stats = locator.cache_stats()
    assert stats["misses"] == 4 and stats["hits"] == 0 and stats["entries"] == 4


def test_direct_locator_caches_its_prepared_pyramids(four_frames):
    locator = OpenCVEccConfig().build()
    locator.register_pairs(four_frames, CHAIN, _eye(3))
    locator.register_pairs(four_frames, EXTRA, _eye(2))
    stats = locator.cache_stats()
    assert stats["pyramid_misses"] == 4 and stats["pyramid_hits"] == 2 + 4


def test_a_locator_told_frames_are_used_once_hashes_none(four_frames, monkeypatch):
    """The mosaic scheme registers each frame once: its locators skip the content keys."""
    from photonpano.plugins.locators import common

    hashed = []
    original = common.frame_key
    monkeypatch.setattr(common, "frame_key", lambda *a, **k: hashed.append(1) or original(*a, **k))
    config = OpenCVEccConfig(**OpenCVEccConfig.template_defaults)
    once = config.build()
    found = once.register_pairs(four_frames, CHAIN, _eye(3), LocatorContext(reuses_frames=False))
    assert not hashed and once.cache_stats()["hits"] == 0
    reused = config.build().register_pairs(four_frames, CHAIN, _eye(3))
    assert hashed  # the default keys every frame by content
    np.testing.assert_array_equal(found.homographies, reused.homographies)


def test_end_of_level_drops_the_cached_data_and_keeps_the_counters(four_frames):
    locator = OpenCVSiftConfig(refine="lm").build()
    locator.register_pairs(four_frames, CHAIN, _eye(3))
    assert locator.cache_stats()["entries"] == 4
    locator.end_level()  # the framework, when a level's registrations are done
    stats = locator.cache_stats()
    assert stats["entries"] == 0 and stats["features_misses"] == 4
    locator.register_pairs(four_frames, EXTRA, _eye(2))
    assert locator.cache_stats()["features_misses"] == 4 + 4
