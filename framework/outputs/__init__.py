"""Output folders a run can be trusted with: atomic files, a manifest, a lock, checkpoints.

Guarantees (see ``docs/outputs.md``):

- **Atomic files**: every file is written under a temporary name in the output folder
  (``.partial-<pid>-<name>``), flushed to disk and renamed into place (``os.replace``),
  so a file under its final name is always complete.
- **run.json last**: it is written only when every other output is complete; its
  presence means the run is complete.
- **Manifest**: ``manifest.json`` lists every file the run wrote; a name is added
  *before* its file appears, so after a crash the manifest covers every file present.
  ``--force`` removes exactly the previous run's manifest files (never other files).
- **Lock**: ``.photonpano.lock`` (holding the writer's pid) keeps a second run out of
  the folder; a lock left by a killed process is taken over.
- **Nothing before the run can start**: the folder gets its first file when the spec
  is valid and the source is open (:meth:`RunFolder.begin`); a run that fails removes
  what it wrote (an interrupted one keeps its checkpoints for ``--resume``).
- **Checkpoints**: after each level, ``checkpoints/level_<k>.npz`` holds what the next
  level needs (:class:`Checkpoint`), for ``--resume``.
"""

from ..errors import OutputError  # noqa: F401 (imported from here by pipeline.py)
from .checkpoint import CHECKPOINTS, Checkpoint
from .files import atomic_path, json_default, save_npy, write_text
from .folder import LOCK, MANIFEST, RUN_JSON, RunFolder

__all__ = ["MANIFEST", "LOCK", "CHECKPOINTS", "RUN_JSON", "atomic_path", "save_npy", "write_text",
           "json_default", "Checkpoint", "RunFolder"]
