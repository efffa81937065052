"""Hostile specs: alias bombs, duplicate keys, bad bytes, huge values, --set blame; one line each."""

from __future__ import annotations

import resource
import time

import pytest
from robust import assert_one_line_error, digests, invoke

BOMB = "source: simulate\n" + "a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(
    f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]\n" for i in range(1, 10))
SET_BOMB = ("locator.ratio=[&a [1,1,1,1,1,1,1,1,1,1], &b [*a,*a,*a,*a,*a,*a,*a,*a,*a,*a], "
            "&c [*b,*b,*b,*b,*b,*b,*b,*b,*b,*b], [*c,*c,*c,*c,*c,*c,*c,*c,*c,*c,*c]]")

SPEC_CASES = {
    # name: (file bytes, --set overrides, expected pieces of the one-line message)
    "alias bomb": (BOMB.encode(), [], ["expands to more than"]),
    "recursive alias": (b"source: simulate\nx: &a [1, *a]\n", [], ["recursive YAML alias"]),
    "deep nesting": (b"source: simulate\nx: " + b"[" * 300 + b"]" * 300 + b"\n", [], ["nested"]),
    "duplicate top-level key": (b"source: simulate\nlevels: 2\nlevels: 3\n", [],
                                ["line 3: duplicate key 'levels' (first on line 2)"]),
    "duplicate nested key": (b"source: simulate\nlocator:\n  plugin: opencv-sift\n  ratio: 0.7\n"
                             b"  ratio: 0.8\n", [], ["line 5: duplicate key 'ratio'"]),
    "invalid utf-8": (b"source: simulate\nlevels: \xff\xfe\n", [], ["line 2: not valid UTF-8", "0xff"]),
    "utf-16 file": ("source: simulate\n".encode("utf-16"), [], ["not valid UTF-8"]),
    "control character in a key": (b"source: simulate\nlev\x01els: 2\n", [], ["line 2", "U+0001"]),
    "escaped control character in a key": (b'source: simulate\n"lev\\x07els": 2\n', [],
                                           ["line 2", "key 'lev\\x07els'", "U+0007"]),
    "nul byte": (b"source: simulate\nlevels: 2\x00\n", [], ["line 2", "NUL byte"]),
    "escaped nul in a key": (b'source: simulate\n\n"a\\0b": 2\n', [], ["line 3", "key 'a\\x00b'"]),
    "escaped nul in a value": (b'source: {plugin: npy, path: "cube\\0.npy"}\n', [], ["line 1", "NUL"]),
    "set control character in a key": (b"source: simulate\n", ["lev\x07els=2"], ["--set", "control character"]),
    "python tag": (b"source: !!python/object/apply:os.system ['echo owned']\n", [], ["not valid YAML"]),
    "syntax error": (b"source: simulate\nlevels: [1, 2\n", [], ["not valid YAML"]),
    "tab indentation": (b"source:\n\tplugin: simulate\n", [], ["line 2", "not valid YAML"]),
    "list instead of mapping": (b"- source\n- levels\n", [], ["must be a mapping"]),
    "scalar instead of mapping": (b"42\n", [], ["must be a mapping"]),
    "huge bad value": (b"source: simulate\nlevels: '" + b"x" * 1_000_000 + b"'\n", [], ["levels", "..."]),
    "huge key": (b"source: simulate\n" + b"k" * 1000 + b": 1\n", [], ["k" * 20]),
    "nan scale": (b"source: simulate\nscale: .nan\n", [], ["scale"]),
    "unknown plugin": (b"source: simulate\nlocator: opencv-sfit\n", [], ["did you mean 'opencv-sift'"]),
    "huge plugin name": (b"source: simulate\nlocator: '" + b"z" * 100_000 + b"'\n", [], ["unknown plugin"]),
    "set alias bomb": (b"source: simulate\n", [SET_BOMB], ["--set", "expands to more than"]),
    "set bad value blamed on --set": (b"source: simulate\nlevels: 2\n", ["levels=abc"],
                                      ["--set 'levels=abc'", "levels"]),
    "set bad field blamed on --set": (b"source: simulate\n", ["locator.ratio=high"],
                                      ["--set 'locator.ratio=high'", "ratio"]),
    "set unknown plugin blamed on --set": (b"source: simulate\n", ["locator=nope"],
                                           ["--set 'locator=nope'", "unknown plugin"]),
    "set without '='": (b"source: simulate\n", ["levels"], ["--set 'levels'", "expected stage.field=value"]),
    "set huge value": (b"source: simulate\n", ["levels=" + "9" * 200_000], ["--set", "levels"]),
    "set huge bad string": (b"source: simulate\n", ["group_size=" + "y" * 200_000], ["--set", "group_size"]),
}


@pytest.mark.parametrize("name", SPEC_CASES)
def test_hostile_spec_is_one_bounded_line(tmp_path, name):
    content, overrides, pieces = SPEC_CASES[name]
    spec = tmp_path / "spec.yaml"
    spec.write_bytes(content)
    before = digests(spec)
    args = ["validate", spec]
    for item in overrides:
        args += ["--set", item]
    start = time.perf_counter()
    line = assert_one_line_error(invoke(*args), *pieces)
    assert time.perf_counter() - start < 10
    assert "--set" in line or str(spec) in line
    assert digests(spec) == before


def test_alias_bomb_stays_small_in_memory(tmp_path):
    """The audit's 9x9 alias bomb grew validate to ~6 GB; now it is refused before expansion."""
    spec = tmp_path / "bomb.yaml"
    spec.write_text(BOMB)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    assert_one_line_error(invoke("validate", spec), "expands to more than")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # KiB


def test_many_invalid_values_are_listed_up_to_a_bound(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: simulate\npair_offsets: [" + ", ".join(["-1"] * 5000) + "]\n")
    result = invoke("validate", spec)
    assert result.exit_code == 1 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert lines[0].startswith(f"error: {spec}: invalid pipeline spec (5000 problems)")
    assert len(lines) <= 22 and lines[-1].strip() == "... and 4980 more"


def test_missing_and_folder_specs(tmp_path):
    assert_one_line_error(invoke("validate", tmp_path / "missing.yaml"), "missing.yaml", "cannot read spec")
    assert_one_line_error(invoke("validate", tmp_path), str(tmp_path), "cannot read spec")


def test_a_valid_spec_still_validates(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("source: simulate\nbase: &b {ratio: 0.7}\n")  # one alias is fine, unknown key is not
    assert_one_line_error(invoke("validate", spec), "base")
    spec.write_text("source: &s {plugin: simulate}\nlocator: {plugin: opencv-sift, ratio: 0.6}\n")
    result = invoke("validate", spec)
    assert result.exit_code == 0, result.stderr
