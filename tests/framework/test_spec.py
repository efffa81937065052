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
