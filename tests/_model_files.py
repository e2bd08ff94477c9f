"""Hostile model files for tests: a real model file edited and sealed again with a valid checksum, so that it passes
every integrity check and only the loader's checks of what it says can refuse it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from safetensors import safe_open
from safetensors.numpy import save

from fusion.modelfile import FORMAT_NAME, content_digest


def rewrite(src: Path, dst: Path, edit=None, *, replace=None) -> Path:
    """``src`` with ``edit(description, arrays)`` applied (in place), or its description replaced by
    ``replace(description)`` (anything JSON can hold, even None), written to ``dst`` with a valid checksum."""
    with safe_open(str(src), framework="numpy") as f:
        description = json.loads(f.metadata()[FORMAT_NAME].partition(" ")[2])
        arrays = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 -- a safe_open, not a dict
    if edit is not None:
        edit(description, arrays)
    if replace is not None:
        description = replace(description)
    arrays = {k: np.array(v, order="C", copy=True) for k, v in arrays.items()}
    text = json.dumps(description)
    Path(dst).write_bytes(save(arrays, metadata={FORMAT_NAME: f"{content_digest(text, arrays)} {text}"}))
    return Path(dst)
