"""Reading a tactile dataset store: lazy arrays, SequenceBatch, a PyTorch Dataset and seeded splits.

Only objects with a complete record are part of the dataset: sequence indices 0..len-1 run over their
rows in store order, ``object_names`` lists them, and failed or unfinished objects are listed in
``failed`` / ``incomplete``. Every read checks the chunks it touches (present, not empty, checksum): a damaged
object raises :class:`DatasetError` naming it, never reads as zeros (see :mod:`tactile.dataset.store`); and the rows
it reads are held to physical bounds (no NaN or Inf, positions within 1 km, unit normals: a store forged around its
digests is refused too, :func:`~tactile.dataset.store.value_problem`).
"""

from __future__ import annotations

import logging
from itertools import pairwise
from pathlib import Path

import numpy as np

from perception.errors import DataLeakError, DatasetError, InvalidArgumentError
from tactile.dataset.store import (
    RECORDS,
    ROW_CHECKED_ARRAYS,
    ZARR_READ,
    array_digest,
    check_arrays,
    damage_message,
    decode_frames,
    decode_row_checksums,
    interest_points_of,
    layout_of,
    read_attrs,
    read_records,
    read_rows,
    row_checksums,
    rows_per_file,
    settings_digest,
    update_digest,
    value_problem,
    written_with_other_settings,
)
from tactile.explore import SequenceBatch, sequence_nbytes

log = logging.getLogger(__name__)

#: Per-probe arrays a SequenceBatch / torch item carries besides the frames.
PROBE_ARRAYS = ("normals", "positions", "tangents", "pad_sides_mm")


def _read_rows(path: Path, name: str, array, rows: np.ndarray, owner) -> np.ndarray:
    """``array[rows]`` for sorted or unsorted ``rows``, reading one contiguous range per chunk file (zarr's point
    selection on sharded arrays decodes a shard per point; ranges decode each chunk once), every chunk checked
    (:func:`~tactile.dataset.store.read_rows`; ``owner(row)`` names the object in errors).

    Raises:
        DatasetError: a missing or damaged chunk.
    """
    import zarr

    out = np.empty((len(rows), *array.shape[1:]), dtype=array.dtype)
    if not len(rows):
        return out
    block = rows_per_file(array)
    increasing = bool((rows[1:] > rows[:-1]).all())  # the common case (all rows, an object's): no sort, no copies
    order = None if increasing else np.argsort(rows, kind="stable")
    sorted_rows = rows if increasing else rows[order]
    files = sorted_rows // block
    bounds = [0, *(np.flatnonzero(files[1:] != files[:-1]) + 1).tolist(), len(rows)]
    with zarr.config.set(ZARR_READ):
        for p, q in pairwise(bounds):
            lo, hi = int(sorted_rows[p]), int(sorted_rows[q - 1]) + 1
            if increasing and hi - lo == q - p:  # rows lo..hi-1, in order: decoded where they go
                read_rows(path, name, array, lo, hi, owner(lo), out=out[p:q])
                continue
            values = read_rows(path, name, array, lo, hi, owner(lo))[sorted_rows[p:q] - lo]
            out[slice(p, q) if increasing else order[p:q]] = values
    return out


def check_disjoint_splits(object_ids, train, test, what: str, mesh_ids=None, by_object: bool = True) -> None:
    """Refuse a split whose train and test share a sequence index or, with ``by_object``, an object (``object_ids``:
    per sequence) or a mesh (``mesh_ids``: per object id, e.g. a file's SHA-256): what every held-out split and
    every unseen-object split goes through before it is returned.

    Raises:
        DataLeakError: naming ``what`` and what train and test share.
    """
    train, test = np.asarray(train, dtype=np.int64), np.asarray(test, dtype=np.int64)
    shared = np.intersect1d(train, test)
    if len(shared):
        raise DataLeakError(f"{what}: {len(shared)} sequences are in both train and test")
    if not by_object:
        return
    ids = np.asarray(object_ids)
    both = np.intersect1d(ids[train], ids[test])
    if len(both):
        raise DataLeakError(f"{what}: objects {both[:5].tolist()} are in both train and test")
    if mesh_ids is not None:
        meshes = np.asarray(mesh_ids, dtype=object)
        same = set(meshes[np.unique(ids[train])]) & set(meshes[np.unique(ids[test])])
        if same:
            raise DataLeakError(f"{what}: {len(same)} mesh(es) are in both train and test (identical files)")


#: How many ``made_from`` links :func:`_made_of` follows (a store's settings are untrusted: no unbounded walk).
MAX_MADE_FROM = 16
#: Mesh files up to this size are told apart by content, larger ones by path: a constant, not the ``file_mb`` limit,
#: so that which objects count as one (and so the folds) does not depend on a reader's environment.
MAX_HASHED_BYTES = 1 << 30


def _made_of(obj: dict, where: str, digests: dict | None = None) -> str:
    """The id :meth:`TactileDataset.mesh_ids` gives the object described by ``obj`` (a store's settings entry): that
    of the object at the end of its ``made_from`` links, by file content (a regular file of at most
    :data:`MAX_HASHED_BYTES`, else its path), catalogue pair or name. ``digests``: ids already found, by path (an
    object and its captures read their file once).

    Raises:
        DatasetError: more than :data:`MAX_MADE_FROM` links (``where`` names the store).
    """
    import hashlib

    from perception.untrusted import open_regular

    start = obj
    for _ in range(MAX_MADE_FROM + 1):
        if not isinstance(obj.get("made_from"), dict):
            break
        obj = obj["made_from"]
    else:
        raise DatasetError(f"{where}: object {str(start.get('name'))[:80]!r} is made from a chain of more than "
                           f"{MAX_MADE_FROM} objects")
    if isinstance(obj.get("path"), str):
        path = obj["path"]
        if digests is not None and path in digests:
            return digests[path]
        try:  # a store's paths are untrusted: no FIFO that blocks, no endless device
            with open_regular(path, MAX_HASHED_BYTES) as f:
                found = "sha256:" + hashlib.file_digest(f, "sha256").hexdigest()
        except (OSError, ValueError):
            found = "path:" + path
        if digests is not None:
            digests[path] = found
        return found
    if isinstance(obj.get("catalogue"), list):
        return "catalogue:" + "/".join(map(str, obj["catalogue"]))
    return "name:" + str(obj.get("name"))


class TactileDataset:
    """A generated store, opened for reading (see :func:`open_dataset`).

    Attributes:
        path: the store folder.
        attrs: the store metadata (settings, package version, command, creation time).
        class_names, object_names: what ``labels`` and ``object_ids`` index (object_names: complete
            objects only, in store order).
        sensor_spec: the sensor's :meth:`FSRSensor.spec`; probes; grid (rows, cols); strategies.
        labels, object_ids: (S,) int64; sequence_strategies: (S,) str; object_labels: (n_objects,) int64.
        contour_seeds, noise_seeds: (S,) int64: the seed each contour was drawn from and its noise seed.
        failed: {object name: reason} of failed objects; incomplete: names of objects not yet explored.
        max_frame_error: largest |stored - pressed| reading (the quantisation step / 2; 0 if lossless).
    """

    def __init__(self, path: str | Path):
        import zarr

        self.path = Path(path)
        self.attrs = read_attrs(self.path)  # settings checked: types, labels, counts within their limits
        settings = self.attrs["settings"]
        try:
            self._group = zarr.open_group(self.path, mode="r")
        except Exception as exc:  # zarr raises several types for missing/corrupt metadata
            raise DatasetError(f"{self.path}: cannot open the store's arrays ({type(exc).__name__}: {exc})") from exc
        check_arrays(self.path, self._group, settings)  # before anything is sized from the settings
        self._settings = settings
        self._layout = layout_of(settings)
        self._encoding = settings["encoding"]
        self.class_names: tuple[str, ...] = tuple(settings["class_names"])
        self.sensor_spec: dict = dict(settings["sensor"])
        self.probes: int = int(settings["probes"])
        self.grid: tuple[int, int] = (int(self.sensor_spec["rows"]), int(self.sensor_spec["cols"]))
        self.strategies: tuple[str, ...] = tuple(settings["strategies"])
        self.max_frame_error: float = float(self._encoding["max_error"])
        objects = settings["objects"]
        records = read_records(self.path, len(objects))
        complete = [i for i in range(len(objects)) if records.get(i, {}).get("status") == "complete"]
        self.failed = {objects[i]["name"]: records[i].get("reason", "") for i in records
                       if records[i].get("status") == "failed"}
        self.incomplete = tuple(objects[i]["name"] for i in range(len(objects)) if i not in records)
        self._store_objects = np.asarray(complete, dtype=np.int64)
        self._records = records
        self._check_settings_digests(complete)
        self._row_sums: dict[tuple[int, str], np.ndarray | None] = {}
        self.object_names: tuple[str, ...] = tuple(objects[i]["name"] for i in complete)
        self.object_labels = np.array([self.class_names.index(objects[i]["label"]) for i in complete], np.int64)
        block = self._layout.block
        self._rows = (self._store_objects[:, None] * block + np.arange(block)[None, :]).ravel()
        self.object_ids = np.repeat(np.arange(len(complete), dtype=np.int64), block)
        self.labels = self.object_labels[self.object_ids] if len(complete) else np.zeros(0, np.int64)
        within = np.tile(np.arange(block) // self._layout.contours, len(complete))
        self.sequence_strategies = np.asarray(self.strategies, dtype=str)[within] if len(complete) else (
            np.zeros(0, dtype=str))
        self._frames = self._group["frames"]
        self.contour_seeds = self._column("contour_seeds")
        self.noise_seeds = self._column("noise_seeds")
        self._check_identities(within)

    def _check_identities(self, within: np.ndarray) -> None:
        """The stored labels, object ids and strategies of every complete row (read, so their checksums are checked
        too) must be what the settings say: a label, class list or object list edited in ``zarr.json`` is refused.

        Raises:
            DatasetError: naming the first object whose stored rows contradict the settings.
        """
        expected = {
            "labels": self.labels,
            "object_ids": self._store_objects[self.object_ids] if len(self._rows) else self.object_ids,
            "strategies": within,
        }
        for name, values in expected.items():
            stored = self._column(name)
            bad = np.flatnonzero(stored != values)
            if len(bad):
                raise DatasetError(
                    f"{self.path}: object {self._owner(self._rows[bad[0]])!r}: its stored {name} "
                    f"({int(stored[bad[0]])}) contradict the store's settings ({int(values[bad[0]])}): the metadata "
                    "was edited or the store is damaged; regenerate it"
                )

    def _check_settings_digests(self, complete: list[int]) -> None:
        """Every complete record that holds the digest of the settings its rows were written with must hold this
        store's: settings edited in ``zarr.json`` since (a frame scale, a sensor range) are refused.

        Raises:
            DatasetError: naming the first object whose record holds another digest.
        """
        current = settings_digest(self._settings)
        other = [i for i in complete if written_with_other_settings(self._records[i], current)]
        if not other:
            return
        first = (f"{self.path}: object {self._settings['objects'][other[0]]['name']!r} was written with other settings "
                 "than the store's zarr.json now holds")
        if len(other) == len(complete):
            raise DatasetError(f"{first}, as was every object ({len(complete)}): the metadata was edited; regenerate "
                               "the store")
        # Some objects only: their records are the likelier damage, and generate explores damaged objects again.
        raise DatasetError(f"{first}, as were {len(other) - 1} of the {len(complete) - 1} other complete objects: their "
                           "records are damaged or the metadata was edited. `visuotactile verify` lists them; "
                           "re-running `visuotactile generate` with the store's settings explores them again")

    def row_checksums(self, name: str, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(expected (N,) uint32, known (N,) bool): the record's checksum of each store row in ``rows`` of array
        ``name`` (:data:`~tactile.dataset.store.ROW_CHECKED_ARRAYS`); ``known`` is False for rows of objects
        whose record was written before records held them.

        Raises:
            DatasetError: a record whose row checksums are malformed, naming its object.
        """
        block = self._layout.block
        rows = np.asarray(rows, dtype=np.int64)
        objects, which = np.unique(rows // block, return_inverse=True)
        sums = [self._object_row_sums(int(obj), name) for obj in objects]
        table = np.stack([np.zeros(block, np.uint32) if s is None else s for s in sums]) if sums else (
            np.zeros((0, block), np.uint32))
        known = np.array([s is not None for s in sums], dtype=bool)[which]
        return table[which, rows % block], known

    def _object_row_sums(self, obj: int, name: str) -> np.ndarray | None:
        """(block,) the row checksums of array ``name`` in store object ``obj``'s record (parsed once), or None for
        a record written before records held them."""
        key = (obj, name)
        if key not in self._row_sums:
            record = self._records.get(obj, {})
            text = record.get("row_checksums")
            where = f"{self.path}: object {self._owner(obj * self._layout.block)!r}: its record"
            if "row_checksums" not in record:  # written before records held them (null is damage)
                self._row_sums[key] = None
            elif not isinstance(text, dict) or name not in text:
                raise DatasetError(f"{where} has no row checksums of {name}: the record was edited or damaged; "
                                   "regenerate the store")
            else:
                self._row_sums[key] = decode_row_checksums(text[name], self._layout.block, f"{where}'s {name}")
        return self._row_sums[key]

    def _check_rows(self, name: str, rows: np.ndarray, values: np.ndarray) -> None:
        """Compare each row read of array ``name`` with its record's checksum (where it has them).

        Raises:
            DatasetError: naming the object and the row whose bytes are not those written there.
        """
        if name not in ROW_CHECKED_ARRAYS or not len(rows):
            return
        expected, known = self.row_checksums(name, rows)
        if not known.any():
            return
        every = known.all()  # the common case: no copy of the rows
        found = row_checksums(values if every else values[known], values.dtype)
        bad = np.flatnonzero(found != (expected if every else expected[known]))
        if len(bad):
            row = int((rows if every else rows[known])[bad[0]])
            problem = (f"its {name} row {row % self._layout.block} differs from the checksum in its record (a chunk "
                       "moved from elsewhere or missing)")
            raise DatasetError(damage_message(self.path, self._owner(row), problem))

    def _column(self, name: str) -> np.ndarray:
        return self._read(name, self._rows)

    def _owner(self, row: int) -> str:
        """The name of the object a store row belongs to."""
        return str(self._settings["objects"][int(row) // self._layout.block]["name"])

    def _read(self, name: str, rows: np.ndarray) -> np.ndarray:
        """Store rows ``rows`` of array ``name``, checked: a damaged chunk raises DatasetError naming its object, and
        every object whose rows are all read must match the digest in its record (a chunk swapped with another
        object's passes its checksum, not the digest)."""
        array = self._frames if name == "frames" else self._group[name]
        values = _read_rows(self.path, name, array, rows, self._owner)
        self._check_rows(name, rows, values)
        self._check_digests(name, array.dtype, rows, values)
        self._check_values(name, rows, values)
        return values

    def _check_values(self, name: str, rows: np.ndarray, values: np.ndarray) -> None:
        """Hold the rows read of array ``name`` to its physical bounds (:func:`~tactile.dataset.store.value_problem`:
        finite, positions within 1 km, unit normals and tangents, pad sides a sensor can have): rows whose digests were
        forged around NaN or 3e38 are refused here, naming the object, not by a classifier blaming its weights.

        Raises:
            DatasetError: naming the object and the first (lowest) row out of bounds.
        """
        if value_problem(name, values) is None:
            return
        order = np.argsort(rows, kind="stable")  # the lowest row out of bounds, whatever order they were read in
        k, problem = value_problem(name, values[order])
        row = int(rows[order[k]])
        raise DatasetError(damage_message(self.path, self._owner(row),
                                          f"its {name} row {row % self._layout.block} {problem}"))

    def _check_digests(self, name: str, dtype, rows: np.ndarray, values: np.ndarray) -> None:
        """Compare the rows of every object read whole with its record's digest of array ``name``.

        Raises:
            DatasetError: naming the object whose rows differ from its digest.
        """
        block = self._layout.block
        if not len(rows):
            return
        increasing = bool((rows[1:] > rows[:-1]).all())
        order = np.arange(len(rows)) if increasing else np.argsort(rows, kind="stable")
        sorted_rows = rows if increasing else rows[order]
        objects, counts = np.unique(sorted_rows // block, return_counts=True)
        for obj in objects[counts >= block]:
            want = np.arange(obj * block, (obj + 1) * block)
            pos = np.searchsorted(sorted_rows, want)
            if pos[-1] >= len(sorted_rows) or not np.array_equal(sorted_rows[pos], want):
                continue  # not all of its rows were read
            at = order[pos]
            # read in order (all rows, an object's): hash them where they lie, not a copy
            whole = at[-1] - at[0] == block - 1 and (np.diff(at) == 1).all()
            digest = array_digest()
            update_digest(digest, values[at[0]:at[-1] + 1] if whole else values[at], dtype)
            expected = self._records.get(int(obj), {}).get("digests")
            if not isinstance(expected, dict) or digest.hexdigest() != expected.get(name):
                raise DatasetError(damage_message(self.path, self._owner(obj * block),
                                                  f"its {name} rows differ from the digest in its record"))

    def __len__(self) -> int:
        return len(self._rows)

    def __repr__(self) -> str:
        return (
            f"TactileDataset({str(self.path)!r}, sequences={len(self)}, objects={len(self.object_names)}, "
            f"classes={len(self.class_names)}, strategies={self.strategies}, failed={len(self.failed)})"
        )

    # ----------------------------------------------------------------------------------- selection
    def _index(self, index) -> np.ndarray:
        """A checked int64 index array into the sequences (None: all)."""
        if index is None:
            return np.arange(len(self), dtype=np.int64)
        idx = np.asarray(index)
        if idx.dtype == bool:
            if idx.shape != (len(self),):
                raise DatasetError(f"{self.path}: boolean index of shape {idx.shape}, expected ({len(self)},)")
            return np.flatnonzero(idx).astype(np.int64)
        if idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
            raise InvalidArgumentError(f"{self.path}: index must be a 1-D integer or boolean array, got {idx.dtype} {idx.shape}")
        idx = idx.astype(np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= len(self)):
            raise DatasetError(f"{self.path}: index out of range 0..{len(self) - 1}")
        return idx

    def mesh_ids(self) -> np.ndarray:
        """(n_objects,) object: what each complete object is made from, so that identical meshes can be told apart
        from different ones: ``"sha256:<hex>"`` of a mesh file (read when the split is made; its path when it is
        unreadable), ``"catalogue:<class>/<seed>"`` for a built-in object, ``"name:<name>"`` otherwise. A rotated
        copy of a mesh has the same id, and so has an object made from another (``made_from``: a camera capture of
        it), which splits by object keep on the side of what it was made from."""
        if getattr(self, "_mesh_ids", None) is None:
            objects = self._settings["objects"]
            digests: dict[str, str] = {}
            self._mesh_ids = np.asarray([_made_of(objects[int(i)], str(self.path), digests)
                                         for i in self._store_objects], dtype=object)
        return self._mesh_ids

    def indices(self, strategy: str | None = None) -> np.ndarray:
        """Sequence indices (int64, sorted) of one strategy, or all when None.

        Raises:
            DatasetError: a strategy not in the store.
        """
        if strategy is None:
            return np.arange(len(self), dtype=np.int64)
        if strategy not in self.strategies:
            raise DatasetError(f"{self.path}: no strategy {strategy!r}; the store has {list(self.strategies)}")
        return np.flatnonzero(self.sequence_strategies == strategy).astype(np.int64)

    def interest_points(self, object_name: str) -> dict[str, np.ndarray]:
        """{strategy: (K, 3) float64 interest points, mm} that the guided strategies of one object drew from (read
        from its completion record, which no digest covers, so checked:
        :func:`~tactile.dataset.store.interest_points_of`).

        Raises:
            DatasetError: no such complete object, or a record whose interest points are not a mapping of the store's
                strategies to at most ``MAX_INTEREST_POINTS`` finite points within 1 km (naming the store, the object
                and the record file).
        """
        try:
            k = self.object_names.index(object_name)
        except ValueError:
            raise DatasetError(f"{self.path}: no complete object {object_name!r}") from None
        index = int(self._store_objects[k])
        try:
            return interest_points_of(self._records[index], self.strategies)
        except (TypeError, ValueError) as exc:
            raise DatasetError(damage_message(self.path, object_name,
                                              f"its record {RECORDS}/{index:05d}.json: {exc}")) from None

    # ------------------------------------------------------------------------------------- reading
    def contour_ids(self, index=None) -> np.ndarray:
        """(n,) int64 for the sequences at ``index`` (None: all): equal for sequences that touch the same contour of the
        same object (the same plane, whichever way its normal points), e.g. the repeats of a guided plane (ten
        interest points make at most 45 planes), so that a split can keep copies on one side. Ids count from 0 in
        order of first appearance."""
        idx = self._index(index)
        rows = self._rows[idx]
        normals = self._read("plane_normals", rows).astype(np.float64)
        points = self._read("plane_points", rows).astype(np.float64)
        # one sign per plane: the first clearly non-zero component positive
        lead = np.argmax(np.abs(normals) > 1e-6, axis=1)
        sign = np.where(normals[np.arange(len(idx)), lead] < 0, -1.0, 1.0)
        keys = np.column_stack([self.object_ids[idx].astype(np.float64), np.round(normals * sign[:, None], 5),
                                np.round(points, 3)])
        _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(np.argsort(first, kind="stable"), kind="stable")  # ids by first appearance
        return order[inverse.reshape(-1)].astype(np.int64)

    def frames(self, index=None) -> np.ndarray:
        """(n, P, R, C) float32 decoded frames of the sequences at ``index`` (None: all)."""
        idx = self._index(index)
        self._check_memory(len(idx))
        rows = self._rows[idx]
        return decode_frames(self._read("frames", rows), self._encoding)

    def _check_memory(self, n: int) -> None:
        """Refuse (DatasetError) to materialise ``n`` sequences above the memory limit (:mod:`perception.limits`)."""
        from perception.limits import check_bytes

        per = sequence_nbytes(self.probes, *self.grid, taxel_bytes=6) + 64  # uint16 codes + float32 frames
        check_bytes(n * per, f"{self.path}: reading {n} sequences ({self.probes} probes x {self.grid[0]} x "
                             f"{self.grid[1]} taxels)", DatasetError)

    def load(self, index=None) -> SequenceBatch:
        """The sequences at ``index`` (None: all), materialised as a :class:`SequenceBatch` (frames decoded
        to float32: 100 KB per 25 x 32 x 32 sequence; use :meth:`torch_dataset` for stores larger than memory).

        Raises:
            DatasetError: a bad index, or a damaged object among those read.
        """
        idx = self._index(index)
        self._check_memory(len(idx))
        rows = self._rows[idx]
        read = {name: self._read(name, rows) for name in (*PROBE_ARRAYS, "plane_points", "plane_normals")}
        return SequenceBatch(
            frames=self.frames(idx),
            normals=read["normals"], positions=read["positions"], tangents=read["tangents"],
            pad_sides_mm=read["pad_sides_mm"], plane_points=read["plane_points"],
            plane_normals=read["plane_normals"], labels=self.labels[idx].copy(),
            object_ids=self.object_ids[idx].copy(), class_names=self.class_names,
            object_names=self.object_names, sensor_spec=dict(self.sensor_spec),
        )

    def torch_dataset(self, index=None):
        """A ``torch.utils.data.Dataset`` over the sequences at ``index`` (None: all) that reads each
        sequence's frames chunk on demand (a store larger than memory works; DataLoader workers reopen
        the store). Item i: (frames float32 tensor (P, R, C), {"normals", "positions", "tangents" (P, 3),
        "pad_sides_mm" (P,)} float32 tensors, label int64 tensor). The per-probe arrays (about 2 % of the
        store) are read into memory when the Dataset is made.
        """
        from tactile.dataset.torch_data import TorchTactileDataset

        idx = self._index(index)
        rows = self._rows[idx]
        probe = {name: self._read(name, rows) for name in PROBE_ARRAYS}
        owners = [self._owner(r) for r in rows]
        return TorchTactileDataset(str(self.path), rows, probe, self.labels[idx].copy(), self._encoding, owners,
                                   self.row_checksums("frames", rows))

    # -------------------------------------------------------------------------------------- splits
    @staticmethod
    def _check_fraction(test_fraction: float) -> float:
        if not (isinstance(test_fraction, (int, float)) and 0 < test_fraction < 1):
            raise InvalidArgumentError(f"test_fraction must be in (0, 1), got {test_fraction!r}")
        return float(test_fraction)

    def split_by_sequence(self, test_fraction: float = 0.2, seed: int = 0, index=None) -> tuple[np.ndarray, np.ndarray]:
        """Seeded split of the sequences (at ``index``, default all) into train and test, stratified by class:
        round(test_fraction * n) test sequences of each class's n (the paper's 80/20). Sorted int64 arrays.

        Raises:
            DataLeakError: train and test would share a sequence (checked on what is returned).
            DatasetError: test_fraction outside (0, 1), a bad index, or an empty test or train side.
        """
        train, test = self._split_by_sequence(test_fraction, seed, index)
        check_disjoint_splits(self.object_ids, train, test, f"{self.path}: split by sequence", by_object=False)
        return train, test

    def _split_by_sequence(self, test_fraction: float = 0.2, seed: int = 0, index=None) -> tuple[np.ndarray, np.ndarray]:
        """The unchecked :meth:`split_by_sequence`."""
        test_fraction = self._check_fraction(test_fraction)
        idx = np.unique(self._index(index))
        rng = np.random.default_rng(seed)
        test = []
        for c in np.unique(self.labels[idx]):
            members = rng.permutation(idx[self.labels[idx] == c])
            test.append(members[: round(test_fraction * len(members))])
        test = np.sort(np.concatenate(test)) if test else np.zeros(0, np.int64)
        train = np.setdiff1d(idx, test)
        if not len(test) or not len(train):
            raise DatasetError(
                f"{self.path}: splitting {len(idx)} sequences at {test_fraction} leaves an empty side"
            )
        return train, test

    def _groups_by_class(self, idx: np.ndarray, rng: np.random.Generator) -> list[list[np.ndarray]]:
        """Per class (sorted), the objects present in ``idx`` as groups made from one mesh (:meth:`mesh_ids`: an
        object with its captures, or copies of one file), in a seeded random order; each group is dealt whole. Where
        every object is its own group the order is that of the objects themselves (the folds of stores before
        groups are unchanged)."""
        present = np.unique(self.object_ids[idx])
        mesh = self.mesh_ids()[present]
        out = []
        for c in np.unique(self.object_labels[present]):
            in_class = self.object_labels[present] == c
            by_mesh: dict[str, list[int]] = {}
            for obj, made in zip(present[in_class].tolist(), mesh[in_class].tolist()):
                by_mesh.setdefault(made, []).append(obj)
            # a group is named by its first object; the permutation runs over those names
            groups = {objs[0]: np.array(objs, dtype=np.int64) for objs in by_mesh.values()}
            out.append([groups[int(g)] for g in rng.permutation(np.array(sorted(groups), dtype=np.int64))])
        return out

    def split_by_object(self, test_fraction: float = 0.2, seed: int = 0, index=None) -> tuple[np.ndarray, np.ndarray]:
        """Seeded split by object (test objects unseen in training), stratified by class: of a class's n
        objects, max(1, round(test_fraction * n)) go to test when n >= 2 (a class with one object stays in
        training); objects made from one mesh (:meth:`mesh_ids`: an object and its captures) count as one and go
        together. Returns sorted int64 sequence indices (train, test) within ``index``.

        Raises:
            DataLeakError: train and test would share a sequence, an object or a mesh (checked on what is returned).
            DatasetError: test_fraction outside (0, 1), a bad index, or no class with two objects.
        """
        train, test = self._split_by_object(test_fraction, seed, index)
        check_disjoint_splits(self.object_ids, train, test, f"{self.path}: split by object", self.mesh_ids())
        return train, test

    def _split_by_object(self, test_fraction: float = 0.2, seed: int = 0, index=None) -> tuple[np.ndarray, np.ndarray]:
        """The unchecked :meth:`split_by_object`."""
        test_fraction = self._check_fraction(test_fraction)
        idx = np.unique(self._index(index))
        test_objects = []
        for groups in self._groups_by_class(idx, np.random.default_rng(seed)):
            if len(groups) >= 2:
                test_objects.extend(np.concatenate(groups[: max(1, round(test_fraction * len(groups)))]).tolist())
        if not test_objects:
            raise DatasetError(f"{self.path}: no class has two objects made from different meshes, so no object can "
                               "be held out")
        in_test = np.isin(self.object_ids[idx], test_objects)
        return idx[~in_test], idx[in_test]

    def kfold_by_object(self, k: int = 5, seed: int = 0, index=None) -> list[tuple[np.ndarray, np.ndarray]]:
        """``k`` seeded folds by object, stratified by class: each class's objects (shuffled) are dealt to
        the folds in turn, continuing where the previous class stopped, so every object is tested exactly
        once and fold sizes differ by at most one object; objects made from one mesh (an object and its captures)
        are dealt together, as one. Returns [(train, test)] sorted int64 indices.

        Raises:
            DataLeakError: train and test would share a sequence, an object or a mesh (checked on what is returned).
            DatasetError: k < 2, fewer objects than k, or a bad index.
        """
        folds = self._kfold_by_object(k, seed, index)
        for f, (train, test) in enumerate(folds):
            check_disjoint_splits(self.object_ids, train, test, f"{self.path}: fold {f} of {k} by object",
                                  self.mesh_ids())
        return folds

    def _kfold_by_object(self, k: int = 5, seed: int = 0, index=None) -> list[tuple[np.ndarray, np.ndarray]]:
        """The unchecked :meth:`kfold_by_object`."""
        if isinstance(k, bool) or not isinstance(k, int) or k < 2:
            raise InvalidArgumentError(f"k must be an integer >= 2, got {k!r}")
        idx = np.unique(self._index(index))
        fold_of = {}
        turn = 0
        for groups in self._groups_by_class(idx, np.random.default_rng(seed)):
            for group in groups:
                fold_of.update(dict.fromkeys(group.tolist(), turn % k))
                turn += 1
        if turn < k:
            raise DatasetError(f"{self.path}: {turn} objects (made from different meshes) cannot fill {k} folds")
        folds = np.array([fold_of[int(o)] for o in self.object_ids[idx]], dtype=np.int64)
        return [(idx[folds != f], idx[folds == f]) for f in range(k)]


def open_dataset(path: str | Path) -> TactileDataset:
    """Open a store made by :func:`tactile.dataset.generate` for reading.

    Raises:
        DatasetError: ``path`` is missing, not a dataset store, of another format version, or unreadable.

    Examples:
        >>> import tempfile
        >>> from tactile.dataset import generate
        >>> from tactile.sensor import FSRSensor
        >>> out = tempfile.mkdtemp() + "/small.zarr"
        >>> _ = generate([("box", 0), ("can", 0)], out, strategies="blind", contours_per_object=3, probes=5,
        ...              sensor=FSRSensor(rows=8, cols=8), workers=1, progress=False)
        >>> ds = open_dataset(out)
        >>> ds.class_names, ds.object_names
        (('box', 'can'), ('box/0', 'can/0'))
        >>> train, test = ds.split_by_sequence(0.5, seed=0)
        >>> batch = ds.load(train)  # a SequenceBatch: frames (S, P, rows, cols) float32
        >>> batch.frames.shape, len(train) + len(test)  # half of each class's 3, rounded up, held out
        ((2, 5, 8, 8), 6)
    """
    path = Path(path)
    try:
        is_dir = path.is_dir()
    except OSError as exc:  # e.g. a name too long for the system: refused as any other bad path
        raise DatasetError(f"{str(path)[:200]}: no such dataset store ({exc.strerror})") from None
    if not is_dir:
        raise DatasetError(f"{path}: no such dataset store (a folder made by generate())")
    return TactileDataset(path)


__all__ = ["PROBE_ARRAYS", "TactileDataset", "open_dataset"]
