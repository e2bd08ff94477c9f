"""What a store's rows depend on beyond its settings: the code that generated them.

Two stores of the same settings made by other code (a change to the pad, the contours, saliency) hold other rows.
:func:`generation_code_version` digests that code, so a store made by other code is told apart: the experiments name
their stores after it (:func:`fusion.experiments.data.store_record`), so an output folder's old store is never read
as the current code's, and :func:`~tactile.dataset.generate` records it and warns when it resumes a store begun by
other code.
"""

from __future__ import annotations

import functools
from pathlib import Path

from perception.runtime import sources_digest

#: Libraries a store's rows depend on (ray casting, meshes and the catalogue's solids, saliency, filters, the
#: encoding): another version of one is other generation code.
GENERATION_LIBRARIES = ("numpy", "scipy", "open3d", "pymeshlab", "manifold3d", "zarr", "numcodecs")


@functools.cache
def generation_code_version() -> str:
    """The digest (:func:`perception.runtime.sources_digest`) of the ``tactile`` and ``perception`` packages, the
    code every row of a store comes from, and of :data:`GENERATION_LIBRARIES`. Read once per process: the code that
    runs is the code that was imported. Conservative: an edit to a module generation does not use (the reader, a
    docstring) also changes it, so at worst a store is generated again."""
    import perception
    import tactile

    return sources_digest({"perception": Path(perception.__file__).resolve().parent,
                           "tactile": Path(tactile.__file__).resolve().parent}, GENERATION_LIBRARIES)


__all__ = ["GENERATION_LIBRARIES", "generation_code_version"]
