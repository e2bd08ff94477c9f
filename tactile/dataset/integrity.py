"""Checking a store for damage: every complete object's chunks (present, not empty, checksums) and digests.

A complete object is intact when every chunk file holding its rows exists and is not empty, every chunk passes
its CRC-32C checksum, the SHA-256 of each array's rows equals the digest in its completion record, the record's
row checksums and settings digest (where it holds them) are those of its rows and of the store's settings, and its
rows and interest points lie within their physical bounds (finite, positions within 1 km, unit normals: what a
forger who recomputed the digests could still get wrong; :func:`~tactile.dataset.store.value_problem`) (see
:mod:`tactile.dataset.store`). Every array must be a zarr v3 one (a v2 ``.zarray`` is refused, naming it).
:func:`verify_store` checks all of them (``visuotactile verify``);
:func:`damaged_objects` is what ``generate`` runs before resuming, to re-explore exactly the damaged ones.
Checking reads the whole store once (decompression and hashing: about the speed of loading it).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from perception.errors import DatasetError
from perception.runtime import progress_bar
from tactile.dataset.store import (
    ARRAYS,
    RECORDS,
    ROW_CHECKED_ARRAYS,
    ZARR_READ,
    array_digest,
    check_arrays,
    decode_row_checksums,
    interest_points_of,
    layout_of,
    read_attrs,
    read_json,
    read_records,
    read_rows,
    row_checksums,
    rows_per_file,
    settings_digest,
    update_digest,
    value_problem,
    written_with_other_settings,
)

log = logging.getLogger(__name__)


@dataclass
class VerifyReport:
    """What :func:`verify_store` found.

    Attributes:
        path: the store.
        objects: objects in the store's settings.
        checked: complete objects checked.
        damaged: {object name: what is wrong} (missing or damaged chunks, rows differing from their digests,
            unreadable completion records).
        incomplete: objects not yet explored (no record); failed: {object name: reason} recorded by generate.
        seconds: wall time of the check, s.
    """

    path: Path
    objects: int
    checked: int = 0
    damaged: dict[str, str] = field(default_factory=dict)
    incomplete: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        """True when no object is damaged (incomplete and failed objects are not damage)."""
        return not self.damaged

    def to_dict(self) -> dict:
        return {"path": str(self.path), "objects": self.objects, "checked": self.checked, "ok": self.ok,
                "damaged": dict(self.damaged), "incomplete": list(self.incomplete), "failed": dict(self.failed),
                "seconds": round(self.seconds, 3)}


def _arrays(path: Path, settings: dict) -> dict:
    """The store's arrays, opened for reading, their shapes and dtypes checked against the settings (what chunk
    sizes are bounded by, :func:`~tactile.dataset.store.max_chunk_file_bytes`)."""
    import zarr

    arrays = {}
    for name in ARRAYS:
        try:
            arrays[name] = zarr.open_array(f"{path}/{name}", mode="r")  # zarr v2 too: check_arrays refuses it
        except Exception as exc:  # noqa: BLE001 -- zarr raises several types for missing or corrupt metadata
            raise DatasetError(f"{path}: cannot open the store's {name!r} array ({type(exc).__name__}: "
                               f"{str(exc)[:160]})") from None
    check_arrays(path, arrays, settings)  # shapes, dtypes, and zarr v3 (a v2 array has no checksums)
    return arrays


def object_damage(path: Path, arrays: dict, settings: dict, index: int, record: dict) -> str | None:
    """What is wrong with complete object ``index`` of the store (None: intact)."""
    import zarr

    layout = layout_of(settings)
    name = str(settings["objects"][index]["name"])
    digests = record.get("digests")
    if not isinstance(digests, dict):
        return "its completion record holds no digests"
    problems = []
    if written_with_other_settings(record, settings_digest(settings)):
        problems.append("it was written with other settings than the store's zarr.json now holds")
    try:
        interest_points_of(record, settings["strategies"])
    except (TypeError, ValueError) as exc:
        problems.append(f"its record {RECORDS}/{index:05d}.json: {exc}")
    kept = "row_checksums" in record  # absent in records written before they were kept (null is damage)
    sums = record.get("row_checksums")
    # What the rows of the identity arrays must hold (as a reader checks when it opens the store): a forged label
    # with a matching digest is damage here too, so that generate re-explores the object instead of a reader refusing.
    identities = {"labels": settings["class_names"].index(settings["objects"][index]["label"]), "object_ids": index,
                  "strategies": np.arange(layout.block) // layout.contours}
    with zarr.config.set(ZARR_READ):
        for array_name in ARRAYS:
            array = arrays[array_name]
            rows = layout.rows(index)
            digest = array_digest()
            per = rows_per_file(array)
            found = []
            forged = None  # the first row out of its physical bounds (value_problem) or contradicting the settings
            try:
                for lo in range(rows.start, rows.stop, per):  # one chunk file at a time: bounded memory
                    hi = min(lo + per, rows.stop)
                    values = read_rows(path, array_name, array, lo, hi, name)
                    update_digest(digest, values, array.dtype)
                    if kept and array_name in ROW_CHECKED_ARRAYS:
                        found.append(row_checksums(values, array.dtype))
                    bad = value_problem(array_name, values) if forged is None else None
                    if bad is not None:
                        forged = f"its {array_name} row {lo - rows.start + bad[0]} {bad[1]}"
                    if array_name in identities and forged is None:
                        want = np.broadcast_to(identities[array_name], (layout.block,))[lo - rows.start:hi - rows.start]
                        differ = np.flatnonzero(values != want)
                        if len(differ):
                            forged = (f"its stored {array_name} ({int(values[differ[0]])}) contradict the store's "
                                      f"settings ({int(want[differ[0]])})")
            except DatasetError as exc:
                problems.append(str(exc).split(" is damaged: ", 1)[-1].split("; `visuotactile verify", 1)[0])
                continue
            if digest.hexdigest() != digests.get(array_name):
                problems.append(f"its {array_name} rows differ from the digest in its record")
                continue
            if found:  # the rows are intact: the record's row checksums must be theirs
                try:
                    text = sums.get(array_name) if isinstance(sums, dict) else None
                    expected = decode_row_checksums(text, layout.block, "its record")
                except DatasetError:
                    expected = None
                if expected is None or not np.array_equal(expected, np.concatenate(found)):
                    problems.append(f"its record's row checksums of {array_name} are not those of its rows")
            if forged is not None:  # rows as their record says, but no generate() wrote them (forged)
                problems.append(forged)
    return "; ".join(problems) or None


def _unreadable_records(path: Path, n_objects: int) -> list[int]:
    """Indices of objects whose record file exists but cannot be read as a JSON object."""
    bad = []
    for index in range(n_objects):
        file = Path(path) / RECORDS / f"{index:05d}.json"
        if not file.exists():
            continue
        try:  # not a regular file, too large or too deeply nested: unreadable too (read_json)
            if isinstance(read_json(file), dict):
                continue
        except (OSError, ValueError):
            pass
        bad.append(index)
    return bad


def damaged_objects(path: str | Path, progress: bool = False) -> dict[int, str]:
    """{object index: what is wrong} for every complete object of the store that is damaged.

    Raises:
        DatasetError: ``path`` is not a readable store of this format.
    """
    path = Path(path)
    settings = read_attrs(path)["settings"]
    return _damaged_objects(path, settings, read_records(path, len(settings["objects"])), progress)


def _damaged_objects(path: Path, settings: dict, records: dict[int, dict], progress: bool) -> dict[int, str]:
    """:func:`damaged_objects` of a store whose settings and records were read."""
    complete = [i for i in sorted(records) if records[i].get("status") == "complete"]
    arrays = _arrays(path, settings) if complete else {}
    damaged = {}
    for index in progress_bar(complete, enabled=progress and bool(complete), desc="verify", unit="object"):
        problem = object_damage(path, arrays, settings, index, records[index])
        if problem is not None:
            damaged[index] = problem
    return damaged


def verify_store(path: str | Path, progress: bool = False) -> VerifyReport:
    """Check every complete object of the store at ``path`` (chunks, checksums, digests) and its records.

    Returns:
        a :class:`VerifyReport`; ``report.ok`` is False when some object is damaged.

    Raises:
        DatasetError: ``path`` is missing, not a dataset store, of another format, or its arrays cannot be opened.
    """
    start = time.perf_counter()
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: no such dataset store (a folder made by generate())")
    settings = read_attrs(path)["settings"]
    objects = settings["objects"]
    records = read_records(path, len(objects))
    report = VerifyReport(path, len(objects))
    unreadable = set(_unreadable_records(path, len(objects)))
    for index in sorted(unreadable):
        report.damaged[str(objects[index]["name"])] = "its completion record is unreadable"
    for index, problem in _damaged_objects(path, settings, records, progress).items():
        report.damaged[str(objects[index]["name"])] = problem
    report.checked = sum(1 for r in records.values() if r.get("status") == "complete")
    report.failed = {str(objects[i]["name"]): str(r.get("reason", "")) for i, r in sorted(records.items())
                     if r.get("status") == "failed"}
    report.incomplete = [str(objects[i]["name"]) for i in range(len(objects)) if i not in records and i not in unreadable]
    report.seconds = time.perf_counter() - start
    return report


__all__ = ["VerifyReport", "damaged_objects", "object_damage", "verify_store"]
