"""The generation code's version beyond test_generation_version: a moved file, the listing order, each
library, read once per process; resuming a store of earlier code (silent) or of another package version (one
warning); hostile attributes shown short and inert; the experiments' part caches follow the generation
code."""

from __future__ import annotations

import json
import logging
import pathlib
import shutil

import pytest

import perception.runtime
import tactile.dataset
import tactile.dataset.version
from perception.errors import DatasetError
from perception.runtime import sources_digest
from tactile.dataset import generate, generation_code_version
from tactile.dataset.store import ATTRS_KEY
from tactile.dataset.version import GENERATION_LIBRARIES
from tactile.sensor import FSRSensor

ARGS = {"strategies": "blind", "contours_per_object": 2, "sensor": FSRSensor(rows=4, cols=4), "probes": 4,
        "workers": 1, "progress": False}
LOGGER = "tactile.dataset.generate"


def _tree(root: pathlib.Path, files: dict) -> pathlib.Path:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


@pytest.fixture(scope="module")
def made_store(tmp_path_factory):
    """One tiny store made by this code; each test resumes a copy of it."""
    out = tmp_path_factory.mktemp("made") / "s"
    generate([("box", 1)], out, **ARGS)
    return out


def _copy_with(made_store, tmp_path, **edits) -> pathlib.Path:
    """A copy of the made store whose attributes have ``edits`` (a value of ... deletes the key)."""
    out = tmp_path / "s"
    shutil.copytree(made_store, out)
    meta = json.loads((out / "zarr.json").read_text())
    attrs = meta["attributes"][ATTRS_KEY]
    for key, value in edits.items():
        if value is ...:
            del attrs[key]
        else:
            attrs[key] = value
    (out / "zarr.json").write_text(json.dumps(meta))
    return out


# ------------------------------------------------------------------------------------- the digest
# (sources_digest)
def test_moving_a_file_to_another_subfolder_changes_the_digest(tmp_path):
    """The path relative to the root is hashed, not the file's name ."""
    # the same files in the same order, one of them in another subfolder
    a = _tree(tmp_path / "a", {"p/m.py": "v = 1\n", "r/n.py": "w = 2\n"})
    b = _tree(tmp_path / "b", {"q/m.py": "v = 1\n", "r/n.py": "w = 2\n"})
    assert sources_digest({"pkg": a}, GENERATION_LIBRARIES) != sources_digest({"pkg": b}, GENERATION_LIBRARIES)


def test_the_digest_does_not_depend_on_the_order_the_filesystem_lists_files(tmp_path, monkeypatch):
    """Two machines list a folder in other orders (os.scandir order is the filesystem's): the same sources
    digest the same."""
    a = _tree(tmp_path / "a", {"m.py": "x = 1\n", "n.py": "y = 2\n", "sub/o.py": "z = 3\n"})
    first = sources_digest({"pkg": a}, GENERATION_LIBRARIES)
    real = pathlib.Path.rglob
    monkeypatch.setattr(pathlib.Path, "rglob",
                        lambda self, pattern: iter(sorted(real(self, pattern), reverse=True)))
    assert sources_digest({"pkg": a}, GENERATION_LIBRARIES) == first


#: What the rows depend on (ray casting, meshes, saliency, filters, the encoding): written out here, so a
#: library dropped from GENERATION_LIBRARIES is noticed (a parametrization over GENERATION_LIBRARIES itself
#: would shrink).
REQUIRED_LIBRARIES = ("numpy", "scipy", "open3d", "pymeshlab", "manifold3d", "zarr", "numcodecs")


@pytest.mark.parametrize("library", REQUIRED_LIBRARIES)
def test_another_version_of_each_generation_library_changes_the_digest(tmp_path, monkeypatch, library):
    """Each library's installed version is part of the default digest (``versions()`` asked for the libraries,
    none dropped from GENERATION_LIBRARIES). The version is changed where it is read (importlib.metadata)."""
    a = _tree(tmp_path / "a", {"m.py": "x = 1\n"})
    first = sources_digest({"pkg": a}, GENERATION_LIBRARIES)
    real = perception.runtime.version
    monkeypatch.setattr(perception.runtime, "version",
                        lambda name: "999.0.0" if name == library else real(name))
    assert sources_digest({"pkg": a}, GENERATION_LIBRARIES) != first


def test_the_generation_code_version_is_read_once_per_process(monkeypatch):
    """'Read once per process: the code that runs is the code that was imported': a file edited during a long
    run does not change store names between two parts of one run."""
    calls = []
    monkeypatch.setattr(tactile.dataset.version, "sources_digest",
                        lambda roots, libraries: calls.append(roots) or "f" * 16)
    tactile.dataset.version.generation_code_version.cache_clear()
    try:
        assert generation_code_version() == generation_code_version() == "f" * 16
        assert len(calls) == 1
    finally:
        monkeypatch.undo()
        tactile.dataset.version.generation_code_version.cache_clear()  # the real value again for the others
    assert generation_code_version() != "f" * 16


# ----------------------------------------------------------------------------------------------- generate's
# resume
def test_a_store_made_before_generation_code_resumes_silently(made_store, tmp_path, caplog):
    """A store of earlier code has no generation_code attribute: it resumes as before, without a warning."""
    out = _copy_with(made_store, tmp_path, generation_code=...)
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        report = generate([("box", 1)], out, **ARGS)
    assert report.skipped == 1 and report.completed == 0
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_store_of_another_package_version_warns_once(made_store, tmp_path, caplog):
    """Another package version is other generation code too (the digest holds the package's version): one
    warning, the package's, not two."""
    out = _copy_with(made_store, tmp_path, package_version="0.0.1", generation_code="feedfacefeedface")
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        generate([("box", 1)], out, **ARGS)
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING and r.name == LOGGER]
    assert len(warnings) == 1 and "made by visuotactile" in warnings[0].getMessage()
    assert "0.0.1" in warnings[0].getMessage()  # quoted or not


HOSTILE = {
    "dict": {"a": 1},
    "list": [1, 2, 3],
    "null": None,
    "number": 12345,
    "float": 1.5e300,
    "bool": True,
    "empty": "",
    "10MB": "x" * 10_000_000,
    "ANSI": "\x1b[2J\x1b[1;31mpwned\x1b[0m\x07",
    "newline": "abc\nERROR fusion.cli: a forged line",
}


def _inert(message: str) -> bool:
    return "\x1b" not in message and "\x07" not in message and "\n" not in message and "\r" not in message


@pytest.mark.parametrize("value", HOSTILE.values(), ids=HOSTILE.keys())
def test_a_hostile_generation_code_is_shown_short_and_inert(made_store, tmp_path, caplog, value):
    """zarr.json is untrusted: whatever its generation_code holds, resuming either warns with a short,
    printable line naming the store (the value abbreviated, e.g. perception.errors.shown, control characters
    escaped) or refuses the store with a DatasetError naming it. No 10 MB log line, no terminal escape or
    forged log line reaches stderr."""
    out = _copy_with(made_store, tmp_path, generation_code=value)
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        try:
            generate([("box", 1)], out, **ARGS)
        except DatasetError as exc:
            assert str(out) in str(exc) and len(str(exc)) < 2000 and _inert(str(exc))
            return
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and r.name == LOGGER]
    assert len(warnings) == 1
    assert str(out) in warnings[0] and "generation code" in warnings[0]
    assert generation_code_version() in warnings[0]
    assert len(warnings[0]) < 2000, f"a warning of {len(warnings[0]):,} characters"
    assert _inert(warnings[0]), repr(warnings[0][:300])


def test_a_hostile_package_version_is_shown_short_and_inert(made_store, tmp_path, caplog):
    """The package-version warning beside it is as short and inert."""
    out = _copy_with(made_store, tmp_path, package_version="\x1b[31m" + "B" * 5_000_000)
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        generate([("box", 1)], out, **ARGS)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and r.name == LOGGER]
    assert len(warnings) == 1 and len(warnings[0]) < 2000 and _inert(warnings[0])


# ---------------------------------------------------------------------------------------- the experiments'
# caches
def test_the_active_parts_cache_follows_the_generation_code(tmp_path, monkeypatch):
    """A report folder's parts/active.json computed on the stores of other code is computed again
    (Context.cached_part keys every part on the generation code, looked up when called), not read as this
    code's."""
    from fusion.experiments import active
    from fusion.experiments.config import QUICK
    from fusion.experiments.context import Context

    computed = []
    monkeypatch.setattr(active, "active_episodes",
                        lambda ctx, objects, **options: computed.append(1) or {"rows": []})
    monkeypatch.setattr(active, "summarize", lambda result, seed=0: {})
    ctx = Context(tmp_path, 0, QUICK, {}, progress=False)
    active.active_part(ctx, [("box", 0)])
    active.active_part(ctx, [("box", 0)])
    assert len(computed) == 1  # cached: the same code
    for module in (tactile.dataset, tactile.dataset.version):
        monkeypatch.setattr(module, "generation_code_version", lambda: "0123456789abcdef")
    active.active_part(ctx, [("box", 0)])
    assert len(computed) == 2, "parts/active.json of other generation code was read as this code's"
