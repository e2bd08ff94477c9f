"""Explore a store's objects again from its recorded settings and compare the bytes with what the store holds.

:func:`~tactile.dataset.integrity.verify_store` proves that a store's rows are those its records describe; it
cannot tell rows forged or edited together with their checksums and digests, nor a store made by code that
explores differently. Since a store's bytes follow from its settings alone (same seed, same bytes, whatever the
workers), exploring an object again and comparing the digests of its rows does: :func:`rerun_objects`. It compares
with the digests the records hold; :func:`~tactile.dataset.integrity.verify_store` checks the rows against those
digests (``visuotactile verify --rerun`` runs both): together they prove the rows.

Only objects a store names by a mesh file or a catalogue entry are explored again. An object made by a loader
function is skipped: the store names that function, and calling a function a file names would run code the
file chose.
"""

from __future__ import annotations

import reprlib
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from perception.errors import DatasetError, InvalidArgumentError
from perception.runtime import progress_bar
from perception.validate import check_count, check_seed
from tactile.dataset.objects import ObjectSpec
from tactile.dataset.store import create_store, read_attrs, read_records
from tactile.dataset.worker import explore_into_store
from tactile.sensor import FSRSensor


@dataclass
class RerunReport:
    """What :func:`rerun_objects` found.

    Attributes:
        path: the store.
        same: names of the objects explored again to the same bytes.
        differ: {object name: the arrays (and interest points) whose bytes differ}.
        skipped: {object name: why it was not explored again (a loader object, a mesh file not found, a failure)}.
        seconds: wall time, s.
    """

    path: Path
    same: list[str] = field(default_factory=list)
    differ: dict[str, str] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        """True when every object drawn was explored again to the same bytes: one that differs fails, and so does
        one that could not be explored again (a store whose entries were all made loaders must not pass)."""
        return not self.differ and not self.skipped

    def to_dict(self) -> dict:
        return {"path": str(self.path), "ok": self.ok, "same": list(self.same), "differ": dict(self.differ),
                "skipped": dict(self.skipped), "seconds": round(self.seconds, 3)}


def _spec(entry: dict, data: Path | None) -> tuple[ObjectSpec | None, str]:
    """The spec of a store's object entry, or None and why not. With ``data``, a mesh is looked up there first as
    ``<its folder's name>/<its file name>`` (a store made on another machine names that machine's paths)."""
    name, label, rotation = str(entry["name"]), str(entry["label"]), entry.get("rotation_seed")
    if "catalogue" in entry:
        catalogue = entry["catalogue"]
        if not (isinstance(catalogue, list) and len(catalogue) == 2 and isinstance(catalogue[0], str)
                and isinstance(catalogue[1], int) and not isinstance(catalogue[1], bool) and catalogue[1] >= 0):
            return None, (f"its entry in the settings is malformed (catalogue must be [class, seed >= 0], got "
                          f"{reprlib.repr(catalogue)})")
        return ObjectSpec(name, label, catalogue=(catalogue[0], catalogue[1]), rotation_seed=rotation), ""
    if "path" in entry:
        if not isinstance(entry["path"], str):
            return None, f"its entry in the settings is malformed (path must be text, got {reprlib.repr(entry['path'])})"
        path = Path(entry["path"])
        if data is not None and (data / path.parent.name / path.name).is_file():
            path = data / path.parent.name / path.name
        if not path.is_file():
            where = f" nor under {data}" if data is not None else "; give the mesh folder (data=...)"
            state = "is not a regular file" if path.exists() else "is not found"
            return None, f"its mesh {str(path)!r} {state}{where}"
        return ObjectSpec(name, label, path=str(path), rotation_seed=rotation), ""
    return None, f"made by a loader function ({entry.get('loader', '?')}), which is never called from a store"


def rerun_objects(path: str | Path, objects: int = 1, *, seed: int = 0, data: str | Path | None = None,
                  progress: bool = False) -> RerunReport:
    """Explore ``objects`` complete objects of the store at ``path`` (drawn with ``seed``) again with its recorded
    settings, each into a temporary store, and compare their rows' digests and interest points with the store's.

    Args:
        objects: how many complete objects to explore again (all of them if fewer); at least 1.
        data: a mesh folder to find the meshes in, as ``<class folder>/<file>`` (for a store made elsewhere).

    Raises:
        DatasetError: ``path`` is not a readable store. InvalidArgumentError: bad ``objects``, ``seed`` or ``data``.
    """
    start = time.perf_counter()
    objects = check_count(objects, "objects", "rerun_objects")
    seed = check_seed(seed, "rerun_objects", allow_none=False)
    if data is not None and not isinstance(data, (str, Path)):
        raise InvalidArgumentError(f"rerun_objects: data must be a folder path (str or Path), got {type(data).__name__}")
    if data is not None and not Path(data).is_dir():
        raise InvalidArgumentError(f"rerun_objects: data {str(data)!r} is not a folder")
    path = Path(path)
    attrs = read_attrs(path)
    settings = attrs["settings"]
    entries = settings["objects"]
    records = read_records(path, len(entries))
    complete = sorted(i for i, r in records.items() if r.get("status") == "complete")
    rng = np.random.default_rng(seed)
    chosen = sorted(rng.choice(complete, size=min(objects, len(complete)), replace=False).tolist())
    try:
        sensor = FSRSensor.from_spec(settings["sensor"])
    except InvalidArgumentError as exc:  # SensorSpecError: name the store, as every other problem of its settings
        raise DatasetError(f"{path}/zarr.json: malformed store settings: sensor: {exc}") from None
    report = RerunReport(path)
    with tempfile.TemporaryDirectory(prefix="visuotactile-rerun-") as tmp:
        again = Path(tmp) / "store"
        create_store(again, settings, {k: v for k, v in attrs.items() if k not in ("settings", "format")})
        for index in progress_bar(chosen, enabled=progress, desc="rerun", unit="object"):
            name = str(entries[index]["name"])
            try:
                spec, why = _spec(entries[index], None if data is None else Path(data))
            except (DatasetError, KeyError, TypeError, ValueError) as exc:  # an entry generate never writes
                spec, why = None, f"its entry in the settings is malformed ({exc})"
            if spec is None:
                report.skipped[name] = why
                continue
            try:
                record = explore_into_store(str(again), index, spec, settings, sensor)
            except Exception as exc:  # noqa: BLE001 - what generate would record as a failure
                report.skipped[name] = f"exploring it failed: {type(exc).__name__}: {exc}"
                continue
            stored = records[index]
            digests = stored.get("digests")
            digests = digests if isinstance(digests, dict) else {}  # a record edited by hand: nothing agrees
            differ = sorted(k for k, v in record["digests"].items() if digests.get(k) != v)
            if record["interest_points"] != stored.get("interest_points"):
                differ.append("interest points")
            if differ:
                report.differ[name] = ", ".join(differ)
            else:
                report.same.append(name)
    report.seconds = time.perf_counter() - start
    return report


__all__ = ["RerunReport", "rerun_objects"]
