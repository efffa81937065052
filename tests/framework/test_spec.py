import json

import pytest
from photonpano.errors import SpecError
from photonpano.spec import apply_overrides, dump_spec, load_spec, spec_model, validate_spec

SPEC = """\
version: 1
source:
  plugin: npy-cube
  path: capture.npy
locator:
  plugin: opencv-sift
  ratio: 1.5
  n_feature: 3
levels: 3
"""


def _write(tmp_path, text, name="spec.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_defaults_are_the_papers_pipeline(host):
    spec = validate_spec({"source": {"plugin": "npy-cube", "path": "x.npy"}}, host)
    assert (spec.resampler.plugin, spec.merger.plugin, spec.locator.plugin, spec.interpolator.plugin) == (
        "midpoint", "flux-mle", "opencv-sift", "cubic-lk")
    assert (spec.levels, spec.group_size, spec.scale) == (3, "auto", 1.0)


def test_field_errors_name_line_stage_plugin_and_field(tmp_path, host):
    with pytest.raises(SpecError) as info:
        load_spec(_write(tmp_path, SPEC), host)
    text = str(info.value)
    assert "line 7: locator (opencv-sift).ratio: Input should be less than 1 (got 1.5)" in text
    assert "line 8: locator (opencv-sift).n_feature: Extra inputs are not permitted" in text


def test_unknown_plugin_lists_installed_and_suggests(tmp_path, host):
    path = _write(tmp_path, "source: {plugin: npy-cube, path: a.npy}\nlocator:\n  plugin: opencv-sfit\n")
    with pytest.raises(SpecError, match=r"line 2: locator: unknown plugin 'opencv-sfit'; did you mean "
                                        r"'opencv-sift'\? \(installed locators: .*opencv-sift"):
        load_spec(path, host)


def test_missing_source_and_bad_yaml(tmp_path, host):
    with pytest.raises(SpecError, match="source: Field required"):
        load_spec(_write(tmp_path, "levels: 2\n"), host)
    with pytest.raises(SpecError, match="not valid YAML"):
        load_spec(_write(tmp_path, "source: [\n"), host)
    with pytest.raises(SpecError, match="cannot read spec"):
        load_spec(tmp_path / "nope.yaml", host)


def test_overrides_and_shorthand(tmp_path, host):
    path = _write(tmp_path, "source: {plugin: npy-cube, path: a.npy}\nlocator: opencv-sift\n")
    spec = load_spec(path, host, ["locator.ratio=0.6", "levels=2", "source.start=10"])
    assert spec.locator.ratio == 0.6 and spec.levels == 2 and spec.source.start == 10
    with pytest.raises(SpecError, match="expected stage.field=value"):
        apply_overrides({}, ["levels"])


def test_resolved_spec_roundtrips(tmp_path, host):
    spec = validate_spec({"source": {"plugin": "simulate", "frames": 100}}, host)
    again = load_spec(_write(tmp_path, dump_spec(spec)), host)
    assert again.model_dump() == spec.model_dump()


def test_schema_documents_fields(host):
    schema = spec_model(host).model_json_schema()
    text = json.dumps(schema)
    assert "Lowe ratio-test threshold" in text  # field docstrings become descriptions
    sift = schema["$defs"]["OpenCVSiftConfig"]
    assert sift["additionalProperties"] is False
    for name, model in schema["$defs"].items():
        for field, info in model.get("properties", {}).items():
            assert info.get("description") or field == "plugin", f"{name}.{field} has no description"


def test_scale_belongs_to_the_compositor(tmp_path, host):
    source = {"plugin": "npy-cube", "path": "x.npy"}
    spec = validate_spec({"source": source}, host)
    assert (spec.compositor.plugin, spec.compositor.scale) == ("drizzle", 1.0)
    # the top-level key of photonpano 0.1 (and --set scale=2) moves into the compositor
    spec = load_spec(_write(tmp_path, "source: {plugin: npy-cube, path: x.npy}\n"), host, ["scale=2"])
    assert (spec.compositor.plugin, spec.compositor.scale, spec.scale) == ("drizzle", 2.0, 2.0)
    spec = validate_spec({"source": source, "scale": 2, "compositor": "flux-canvas"}, host)
    assert (spec.compositor.plugin, spec.compositor.scale) == ("flux-canvas", 2.0)
    import yaml

    dumped = yaml.safe_load(dump_spec(spec))
    assert "scale" not in dumped and dumped["compositor"]["scale"] == 2.0
    with pytest.raises(SpecError, match="scale is given twice .* write it once, as compositor.scale"):
        validate_spec({"source": source, "scale": 2, "compositor": {"plugin": "drizzle", "scale": 3}}, host)


@pytest.mark.parametrize(("text", "overrides", "expected"), [
    ("source: {plugin: npy-cube, path: a.npy}\nlokator:\n  ratio: 0.7\n", [],
     "line 2: lokator: Extra inputs are not permitted; did you mean 'locator'?"),
    ("source: {plugin: npy-cube, path: a.npy}\n", ["lokator.ratio=0.7"],
     "--set 'lokator.ratio=0.7': lokator: Extra inputs are not permitted; did you mean 'locator'?"),
    ("source: {plugin: npy-cube, path: a.npy}\nlocator: {plugin: opencv-sift, rattio: 0.7}\n", [],
     "line 2: locator (opencv-sift).rattio: Extra inputs are not permitted; did you mean 'ratio'?"),
    ("source: {plugin: npy-cube, path: a.npy}\noutputs: {panorama_pgn: false}\n", [],
     "outputs.panorama_pgn: Extra inputs are not permitted; did you mean 'panorama_png'?"),
    ("source: {plugin: npy-cube, path: a.npy}\nmosaic: {locator: {plugin: opencv-ecc, iteratons: 3}}\n", [],
     "mosaic.locator (opencv-ecc).iteratons: Extra inputs are not permitted; did you mean 'iterations'?"),
])
def test_unknown_field_names_get_did_you_mean(tmp_path, host, text, overrides, expected):
    with pytest.raises(SpecError) as info:
        load_spec(_write(tmp_path, text), host, overrides)
    assert expected in str(info.value)


def test_unknown_field_without_close_match_lists_the_fields(tmp_path, host):
    with pytest.raises(SpecError) as info:
        load_spec(_write(tmp_path, "source: {plugin: npy-cube, path: a.npy}\nmerger: {plugin: flux-mle, zz: 1}\n"),
                  host)
    assert "merger (flux-mle).zz: Extra inputs are not permitted (expected one of: subbatch_px" in str(info.value)


def test_unknown_plugin_does_not_hide_other_errors(tmp_path, host):
    text = ("source: {plugin: npy-cube, path: a.npy}\n"
            "locator: {plugin: opencv-sfit, ratio: 9}\n"
            "levels: 0\n"
            "lokator: {}\n"
            "merger: {plugin: flux-mle, subbatch_pxx: 1}\n")
    with pytest.raises(SpecError) as info:
        load_spec(_write(tmp_path, text), host)
    lines = str(info.value).splitlines()
    assert "(4 problems)" in lines[0]
    assert lines[1].strip().startswith("line 2: locator: unknown plugin 'opencv-sfit'; did you mean 'opencv-sift'?")
    assert lines[2].strip().startswith("line 3: levels: Input should be greater than or equal to 1")
    assert lines[3].strip() == "line 4: lokator: Extra inputs are not permitted; did you mean 'locator'?"
    assert "line 5: merger (flux-mle).subbatch_pxx: Extra inputs are not permitted; did you mean 'subbatch_px'?" \
        in lines[4]
    # the unknown plugin's own fields are not checked against another plugin's fields
    assert not any("ratio" in line for line in lines)


def test_unknown_source_plugin_is_not_also_reported_missing(tmp_path, host):
    with pytest.raises(SpecError) as info:
        load_spec(_write(tmp_path, "source: {plugin: npy-cub, path: a.npy}\nlevels: 9\n"), host)
    text = str(info.value)
    assert "unknown plugin 'npy-cub'; did you mean 'npy-cube'?" in text
    assert "levels: Input should be less than or equal to 8" in text and "Field required" not in text


def _capture(tmp_path, kind):
    """A file or folder a source plugin claims (content irrelevant: it is never read)."""
    import numpy as np

    if kind == "npy":
        np.save(tmp_path / "capture.npy", np.zeros((4, 8, 8), np.uint8))
        return tmp_path / "capture.npy", "npy-cube"
    if kind == "zarr":
        (tmp_path / "capture.zarr").mkdir()
        return tmp_path / "capture.zarr", "zarr-cube"
    if kind == "images":
        (tmp_path / "frames").mkdir()
        (tmp_path / "frames" / "000.png").write_bytes(b"\x89PNG\r\n\x1a\n")
        return tmp_path / "frames", "video"
    names = {"bin": ("capture.bin", "swissspad-bin"), "mraw": ("beam.mraw", "photron-mraw"),
             "mp4": ("clip.mp4", "video")}
    name, plugin = names[kind]
    (tmp_path / name).write_bytes(bytes(range(128, 256)) * 4)  # not UTF-8
    return tmp_path / name, plugin


@pytest.mark.parametrize("kind", ["npy", "zarr", "bin", "mraw", "mp4", "images"])
def test_a_capture_given_as_spec_names_pano(tmp_path, host, kind):
    path, plugin = _capture(tmp_path, kind)
    with pytest.raises(SpecError) as info:
        load_spec(path, host)
    text = str(info.value)
    assert text == (f"{path}: a capture (source {plugin}), not a YAML pipeline spec; reconstruct it with "
                    f"`photonpano pano {path}`")
    assert "UTF-8" not in text and "\n" not in text


def test_a_yaml_spec_is_never_taken_for_a_capture(tmp_path, host):
    spec = load_spec(_write(tmp_path, "source: {plugin: npy-cube, path: a.npy}\n"), host)
    assert spec.source.plugin == "npy-cube"
