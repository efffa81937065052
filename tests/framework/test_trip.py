"""A spec's trip through a run: no framework module other than leaf helpers is entered more than 3 times.

Issue 31 measured the orchestration by following one spec through a run (then: 16
modules, ``binning.py`` entered 5 times, ``spec.py`` 4, going back up 23 times). This
test measures it on a real run, precisely:

- **The run**: ``photonpano.run`` of a 2 000-frame simulated capture at the default flux
  (3 levels: pairwise, then mosaic; binned registration; the panorama, the confidence
  report), serial executor, traced with :func:`sys.setprofile` (Python calls only).
- **An entry into module M** is a call of a function of M (a framework module,
  ``photonpano.*`` outside ``photonpano.plugins``) whose caller is a function of another
  framework module: the innermost framework frame below the call, skipping the frames of
  :mod:`photonpano.executor` (it only runs the caller's callbacks) and of third-party
  libraries (pydantic calling a validator: the caller is who asked pydantic). Not entries:
  calls from plugin code (a plugin's business), module imports, reads of records
  (dataclass-generated methods, properties), and calls of a stage's interface method on a
  stage object (``source.sum_ranges``, ``locator.register_pairs``: the caller calls the
  stage, wherever it is implemented, as it calls a plugin).
- **Counted once per calling unit**: the entries of M are the distinct top-level
  functions or classes of other modules from which control entered M. A unit that enters
  M in a loop (over levels, windows, groups, pairs, frames) or through several of M's
  functions is one step of the trip; so per-frame and per-pair hot loops count once.
- **Leaf helpers** are not counted: modules that hold values and functions of them and
  never call back into a non-leaf framework module (the test checks that they never do):
  :data:`LEAVES`.
- **Going back up**: an entry into M while M is already on the stack below the caller.
  The only ones are the two observer callbacks of a finished level (:data:`UPWARD`).
"""

from __future__ import annotations

import collections
import inspect
import sys

import pytest

LEAVES = {
    "photonpano.geometry": "homography arithmetic on arrays",
    "photonpano.errors": "exception types",
    "photonpano.records": "frozen records (MergedFrames, Groups, LevelResult, ...)",
    "photonpano.guards": "plausibility tests of homographies",
    "photonpano.jit": "the optional numba decorator",
    "photonpano.imaging": "image binning and correlation on arrays",
    "photonpano.types": "pydantic field types",
    "photonpano.host": "the plugin registry and hook bus: every phase asks it for a plugin or fires a hook; "
                       "it calls pluggy and plugin code only",
    "photonpano.progress": "progress bars: a phase starts a task and advances it (through the host's hooks)",
    "photonpano.config": "the base class of stage configs (build, check_available)",
    "photonpano.spec_errors": "wording of spec validation errors",
    "photonpano.watchdog": "the deadline around each plugin call (a context manager every caller of a stage "
                           "wraps the call in): it calls the errors and faults helpers only",
    "photonpano.faults": "wording of plugin faults",
    "photonpano.spec_model": "the spec's schema, and queries of a validated spec (the plugin configs it "
                             "holds, the scheme of each level): it calls the host and the config base only",
}
"""Leaf helper modules and why each is one."""

UPWARD = {("photonpano.reconstruction", "levels:estimate_motion"),
          ("photonpano.pipeline", "reconstruction:reconstruct")}
"""The entries that go back up: a finished level's :class:`~photonpano.records.LevelResult` reaches the
``on_level`` observers of ``reconstruct`` (statistics, checkpoint) and of the pipeline (the
``photonpano_level_finished`` hook)."""


def _module(frame) -> str:
    return frame.f_globals.get("__name__", "")


def _framework(name: str) -> bool:
    return name.startswith("photonpano") and not name.startswith("photonpano.plugins")


class _Trip:
    """Entries per framework module of one traced call (see the module)."""

    def __init__(self) -> None:
        from photonpano import stages

        self.units: dict[str, set[str]] = collections.defaultdict(set)
        self.upward: set[tuple[str, str]] = set()
        self.calls_out: dict[str, set[str]] = collections.defaultdict(set)
        self._data_access: dict[object, bool] = {}
        self._stage_bases = tuple(c for c in vars(stages).values() if inspect.isclass(c) and inspect.isabstract(c)
                                  and c.__module__.startswith("photonpano"))

    def _is_data_access(self, frame) -> bool:
        code = frame.f_code
        if code not in self._data_access:
            name = code.co_qualname
            found = name.startswith("__create_fn__")  # dataclass-generated __init__, __eq__, ...
            if not found and "." in name and "<locals>" not in name:
                owner = sys.modules.get(_module(frame))
                *path, attr = name.split(".")
                for part in path:
                    owner = getattr(owner, part, None)
                found = owner is not None and isinstance(inspect.getattr_static(owner, attr, None), property)
            self._data_access[code] = found
        return self._data_access[code]

    def _is_stage_call(self, frame) -> bool:
        this = frame.f_locals.get("self")
        return isinstance(this, self._stage_bases) and any(
            frame.f_code.co_name in vars(base) for base in type(this).__mro__ if base in self._stage_bases)

    def __call__(self, frame, event, arg) -> None:
        if event != "call" or frame.f_code.co_name == "<module>":
            return
        callee = _module(frame)
        if not _framework(callee) or callee == "photonpano.executor":
            return
        caller = frame.f_back
        while caller is not None:
            name = _module(caller)
            if name.startswith("importlib"):
                return  # a module import
            if name.startswith("photonpano") and name != "photonpano.executor":
                break
            caller = caller.f_back
        if caller is None or caller.f_code.co_name == "<module>":
            return
        source = _module(caller)
        if source == callee or not _framework(source) or self._is_data_access(frame) or self._is_stage_call(frame):
            return
        unit = f"{source.removeprefix('photonpano.')}:{caller.f_code.co_qualname.split('.')[0]}"
        self.calls_out[source].add(callee)
        if callee in LEAVES:
            return
        self.units[callee].add(unit)
        below = caller.f_back
        while below is not None:
            if _module(below) == callee:
                self.upward.add((callee, unit))
                break
            below = below.f_back


@pytest.fixture(scope="module")
def trip() -> _Trip:
    """The trip of a 2 000-frame simulated capture through ``photonpano.run`` (serial executor)."""
    import photonpano

    traced = _Trip()
    spec = {"source": {"plugin": "simulate", "frames": 2000, "seed": 1}, "executor": "serial"}
    sys.setprofile(traced)
    try:
        result = photonpano.run(spec, progress=False)
    finally:
        sys.setprofile(None)
    assert [level["scheme"] for level in result.summary["levels"]] == ["pairwise", "mosaic", "mosaic"]
    assert result.summary["budget"]["register_binning"] > 1  # the binned path is on the trip
    return traced


def _table(trip: _Trip) -> str:
    return "\n".join(f"{len(units):2d} {module}: {', '.join(sorted(units))}"
                     for module, units in sorted(trip.units.items(), key=lambda item: -len(item[1])))


def test_no_module_is_entered_more_than_three_times(trip):
    """Every framework module outside :data:`LEAVES` is entered from at most 3 units of other modules."""
    assert len(trip.units) >= 15, _table(trip)  # the trip was traced: pipeline, levels, schemes, budget, ...
    over = {module: sorted(units) for module, units in trip.units.items() if len(units) > 3}
    assert not over, "entered more than 3 times:\n" + _table(trip)


def test_control_goes_back_up_only_to_the_level_observers(trip):
    """The only upward entries are the two ``on_level`` observer callbacks (:data:`UPWARD`)."""
    assert trip.upward == UPWARD, _table(trip)


def test_leaves_are_leaves(trip):
    """A leaf helper never enters a non-leaf framework module (so its own calls are not steps of the trip)."""
    climbing = {leaf: sorted(m for m in trip.calls_out[leaf] if m not in LEAVES) for leaf in LEAVES}
    assert not any(climbing.values()), climbing
