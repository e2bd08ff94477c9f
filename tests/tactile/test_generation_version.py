"""The generation code's version: a digest of the tactile and perception sources and the libraries' versions, in the
experiments' store names (a folder's store made by other code is not reused) and in a store's attributes (resuming a
store begun by other code warns)."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import perception
import tactile
from fusion.experiments.data import ensure_store, store_record
from perception.runtime import sources_digest
from tactile.dataset import generate, generation_code_version
from tactile.dataset.store import ATTRS_KEY
from tactile.dataset.version import GENERATION_LIBRARIES
from tactile.sensor import FSRSensor


def _tree(root: Path, files: dict) -> Path:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


def test_the_digest_follows_every_python_source_and_nothing_else(tmp_path, monkeypatch):
    a = _tree(tmp_path / "a", {"m.py": "x = 1\n", "sub/n.py": "y = 2\n", "notes.txt": "n"})
    first = sources_digest({"pkg": a}, GENERATION_LIBRARIES)
    assert first == sources_digest({"pkg": a}, GENERATION_LIBRARIES) and len(first) == 16
    (a / "notes.txt").write_text("other")  # not code
    assert sources_digest({"pkg": a}, GENERATION_LIBRARIES) == first
    (a / "sub/n.py").write_text("y = 3\n")  # an edit
    edited = sources_digest({"pkg": a}, GENERATION_LIBRARIES)
    assert edited != first
    (a / "sub/n.py").write_text("y = 2\n")
    assert sources_digest({"pkg": a}, GENERATION_LIBRARIES) == first  # content, not time stamps
    (a / "sub/n.py").rename(a / "sub/o.py")  # a rename
    assert sources_digest({"pkg": a}, GENERATION_LIBRARIES) != first
    (a / "sub/o.py").rename(a / "sub/n.py")
    (a / "new.py").write_text("")  # an added file, even empty
    assert sources_digest({"pkg": a}, GENERATION_LIBRARIES) != first
    (a / "new.py").unlink()
    assert sources_digest({"other": a}, GENERATION_LIBRARIES) != first  # the root's name
    import perception.runtime
    real = perception.runtime.versions
    monkeypatch.setattr(perception.runtime, "versions", lambda *names: {**real(*names), "open3d": "0.0.1"})
    assert sources_digest({"pkg": a}, GENERATION_LIBRARIES) != first  # another library version


def test_the_version_is_the_digest_of_the_tactile_and_perception_sources(tmp_path):
    # copies of the two packages digest to the running version; an edit to the pad's module in the copy does not
    copies = {name: tmp_path / name for name in ("perception", "tactile")}
    for name, package in (("perception", perception), ("tactile", tactile)):
        shutil.copytree(Path(package.__file__).parent, copies[name], ignore=shutil.ignore_patterns("__pycache__"))
    assert sources_digest(copies, GENERATION_LIBRARIES) == generation_code_version()
    touching = copies["tactile"] / "touching.py"
    touching.write_text(touching.read_text() + "\n# an edit\n")
    assert sources_digest(copies, GENERATION_LIBRARIES) != generation_code_version()


def test_a_store_of_other_generation_code_is_another_store(tmp_path, monkeypatch):
    import tactile.dataset

    objects = [("box", 0), ("can", 0)]
    record = store_record(objects, 3, 0, ("blind",))
    assert record["generation_code"] == generation_code_version()
    kwargs = {"strategies": ("blind",), "contours": 3, "seed": 0, "sensor": FSRSensor(rows=4, cols=4), "probes": 4,
              "workers": 1, "progress": False}
    ensure_store(objects, tmp_path, **kwargs)
    monkeypatch.setattr(tactile.dataset, "generation_code_version", lambda: "0123456789abcdef")
    assert store_record(objects, 3, 0, ("blind",))["generation_code"] == "0123456789abcdef"
    ds, other = ensure_store(objects, tmp_path, **kwargs)
    assert other["generation_code"] == "0123456789abcdef"
    stores = sorted(p.name for p in tmp_path.glob("*.zarr"))
    assert len(stores) == 2 and stores[0] != stores[1]  # generated again under its own name, the old one left
    assert len(ds.object_names) == 2


def test_generate_records_the_version_and_warns_when_resuming_another(tmp_path, caplog):
    out = tmp_path / "s"
    args = {"strategies": "blind", "contours_per_object": 2, "sensor": FSRSensor(rows=4, cols=4), "probes": 4,
            "workers": 1, "progress": False}
    generate([("box", 1)], out, **args)
    meta = json.loads((out / "zarr.json").read_text())
    assert meta["attributes"][ATTRS_KEY]["generation_code"] == generation_code_version()
    with caplog.at_level(logging.WARNING, logger="tactile.dataset.generate"):
        generate([("box", 1)], out, **args)
    assert "generation code" not in caplog.text  # the same code: no warning
    meta["attributes"][ATTRS_KEY]["generation_code"] = "feedfacefeedface"
    (out / "zarr.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING, logger="tactile.dataset.generate"):
        generate([("box", 1)], out, **args)
    assert f"{out}: begun by other generation code (feedfacefeedface, now {generation_code_version()})" in caplog.text
