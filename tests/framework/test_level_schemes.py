"""Level schemes: the spec's level_schemes / mosaic section, and the level loop's records."""

import dataclasses

import numpy as np
import pytest
from photonpano.errors import SpecError
from photonpano.host import PluginHost
from photonpano.spec import apply_overrides, dump_spec, level_schemes, validate_spec

HOST = PluginHost()
SOURCE = {"source": {"plugin": "simulate"}}


def _spec(**fields):
    return validate_spec({**SOURCE, **fields}, HOST)


def test_default_schemes_are_pairwise_then_mosaic():
    spec = _spec(levels=4)
    assert level_schemes(spec) == ["pairwise", "mosaic", "mosaic", "mosaic"]
    assert spec.mosaic.locator.plugin == "opencv-ecc" and spec.mosaic.locator.iterations == 10
    assert spec.mosaic.template.plugin == "flux-canvas"


def test_refine_locator_keeps_working_under_its_new_names():
    assert level_schemes(_spec(refine_locator=None, levels=3)) == ["pairwise"] * 3
    spec = _spec(refine_locator={"plugin": "opencv-ecc", "iterations": 5})
    # fields given win, the rest start from the locator's template defaults
    assert spec.mosaic.locator.iterations == 5 and spec.mosaic.locator.pyramid_levels == 1
    assert _spec(refine_locator={"iterations": 7}).mosaic.locator.iterations == 7
    assert "refine_locator" not in dump_spec(spec)
    assert validate_spec({**SOURCE, **_reloaded(spec)}, HOST).model_dump() == spec.model_dump()  # spec.yaml round trip


def _reloaded(spec):
    import yaml

    data = yaml.safe_load(dump_spec(spec))
    data.pop("source")
    return data


@pytest.mark.parametrize("fields, message", [
    ({"level_schemes": ["mosaic"]}, "level 1 must be pairwise"),
    ({"level_schemes": []}, "level_schemes"),
    ({"level_schemes": ["pairwise", "fancy"]}, "level_schemes.1"),
    ({"refine_locator": None, "level_schemes": ["pairwise", "mosaic"]}, "write level_schemes only"),
    ({"refine_locator": "opencv-ecc", "mosaic": {"locator": "opencv-orb"}}, "write mosaic.locator only"),
    ({"mosaic": {"locator": {"plugin": "opencv-ecc", "iterations": 0}}}, "mosaic.locator (opencv-ecc).iterations"),
])
def test_bad_schemes_get_one_clear_message(fields, message):
    with pytest.raises(SpecError) as err:
        _spec(**fields)
    assert message in str(err.value)


def test_set_reaches_the_mosaic_locator():
    data = apply_overrides(SOURCE, ["mosaic.locator.iterations=3", "level_schemes=[pairwise, mosaic, pairwise]"])
    spec = validate_spec(data, HOST)
    assert spec.mosaic.locator.plugin == "opencv-ecc" and spec.mosaic.locator.iterations == 3
    assert level_schemes(spec.model_copy(update={"levels": 4})) == ["pairwise", "mosaic", "pairwise", "pairwise"]


def test_levels_emit_frozen_records_in_panorama_coordinates():
    """Each level's record is frozen, names its scheme, and is in the final gauge.

    The middle frame's homography is the identity, so observers see output coordinates.
    """
    from photonpano.executor import SerialExecutor
    from photonpano.reconstruction import Stages

    spec = _spec(source={"plugin": "simulate", "frames": 2400, "height": 128, "width": 248, "vibration_px": 2},
                 group_size=300, levels=3, outputs={"merged_frames": True})
    source = spec.source.build()
    seen = []
    homographies = Stages(spec, source).estimate_motion(SerialExecutor(), on_level=seen.append)
    assert [r.scheme for r in seen] == ["pairwise", "mosaic", "mosaic"]
    for result in seen:
        np.testing.assert_allclose(result.homographies[len(result.homographies) // 2], np.eye(3), atol=1e-12)
        assert result.merged is not None and len(result.merged) == len(result.groups)  # dumps at every level
        with pytest.raises(dataclasses.FrozenInstanceError):
            result.level = 0
    assert seen[0].located.pair_index is not None and seen[1].located.pair_index is None
    np.testing.assert_array_equal(seen[-1].homographies, homographies)
    stats = seen[1].statistics()
    assert stats["scheme"] == "mosaic" and stats["pairs"] == len(seen[1].groups)


def test_pure_tasks_pickle_with_their_executor_and_progress():
    """What a pure task holds travels to another process.

    Executors as serial ones, progress callables as ones that do nothing (a Dask worker
    has no progress display).
    """
    import pickle

    from photonpano.executor import SerialExecutor, ThreadExecutor
    from photonpano.progress import start_task

    with ThreadExecutor(2) as executor:
        assert type(pickle.loads(pickle.dumps(executor))) is SerialExecutor
        done = []
        assert executor.map(lambda x: x * x, [1, 2, 3], done=done.append) == [1, 4, 9]
    assert sorted(done) == [1, 4, 9]
    pickle.loads(pickle.dumps(start_task("level 1", 3)))(1)  # no display here: nothing happens


def test_interpolator_warm_up_runs_in_the_background_and_its_errors_do_not_stop_the_run():
    """The level loop calls ``Interpolator.warm_up`` off the critical path; a failing warm-up changes nothing."""
    import threading

    from photonpano.executor import SerialExecutor
    from photonpano.reconstruction import Stages

    spec = _spec(source={"plugin": "simulate", "frames": 2400, "height": 128, "width": 248, "vibration_px": 2},
                 group_size=300, levels=2)
    source = spec.source.build()
    reference = Stages(spec, source).estimate_motion(SerialExecutor())
    stages, called = Stages(spec, source), []

    def failing_warm_up():
        called.append(threading.current_thread() is not threading.main_thread())
        raise ImportError("a library the interpolator needs later")

    stages.interpolator.warm_up = failing_warm_up
    np.testing.assert_array_equal(stages.estimate_motion(SerialExecutor()), reference)
    for thread in threading.enumerate():
        if thread.name == "photonpano-warm-up":
            thread.join(10)
    assert called == [True]


def test_merged_frames_content_keys_follow_ids_or_pixels():
    """Equal keys mean identical frames: ids when the producer gives them, else a digest of the pixels."""
    from photonpano.records import MergedFrames
    from photonpano.schemes.pairwise import _MergedRing

    rng = np.random.default_rng(0)
    flux = rng.random((3, 8, 10), dtype=np.float32)
    plain = MergedFrames(flux, np.ones_like(flux), (flux * 255).astype(np.uint8), flux > 0.1)
    copy = MergedFrames(flux.copy(), np.ones_like(flux), (flux * 255).astype(np.uint8), flux > 0.1)
    assert plain.content_key(0) == copy.content_key(0) != plain.content_key(1)
    assert plain.content_key(0, flux=True) != plain.content_key(0)
    first, second = MergedFrames.new_ids(2), MergedFrames.new_ids(1)
    assert len(set(first) | set(second)) == 3
    ring = _MergedRing(4)
    ring.put(np.arange(3), plain)
    keys = [ring.frames.content_key(i) for i in range(3)]
    assert len(set(keys)) == 3
    ring.put(np.array([3, 4]), MergedFrames(*(getattr(plain, f)[:2] for f in ("flux", "frames", "images", "masks"))))
    # group 4 reuses slot 0 with the pixels of the frame already there: it is still new content
    assert ring.frames.content_key(0) != keys[0] and ring.frames.content_key(1) == keys[1]
    both = MergedFrames.concat(ring.frames, ring.frames)
    assert both.ids is not None and both.content_key(5) == ring.frames.content_key(1)
    assert MergedFrames.concat(ring.frames, plain).ids is None
