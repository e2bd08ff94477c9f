"""The PyTorch view of a store (imported only when asked for: torch is slow to import)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from perception.errors import DatasetError
from tactile.dataset.store import damage_message, decode_frames, read_rows, row_checksums


class TorchTactileDataset(Dataset):
    """Sequences of a store, frames read one sequence chunk at a time (see
    :meth:`tactile.dataset.TactileDataset.torch_dataset`). Picklable: each DataLoader worker opens the
    store itself on first use. Each read checks its chunk (a damaged one raises DatasetError naming the object
    in ``owners``) and, with ``checksums`` ((expected, known) per item, from
    :meth:`tactile.dataset.TactileDataset.row_checksums`), the row's bytes against its record's checksum."""

    def __init__(self, path: str, rows: np.ndarray, probe: dict[str, np.ndarray], labels: np.ndarray, encoding: dict,
                 owners: list[str] | None = None, checksums: tuple[np.ndarray, np.ndarray] | None = None):
        self.path, self.rows, self.labels, self.encoding = path, rows, labels, encoding
        self.owners = owners if owners is not None else [f"row {r}" for r in rows]
        self.checksums = checksums
        self.probe = {name: torch.from_numpy(np.ascontiguousarray(values)) for name, values in probe.items()}
        self._frames = None

    def __len__(self) -> int:
        return len(self.rows)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_frames"] = None  # zarr handles are reopened in the worker process
        return state

    def __getitem__(self, i: int):
        if self._frames is None:
            import zarr

            self._frames = zarr.open_array(f"{self.path}/frames", mode="r")
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} sequences")
        row = int(self.rows[i])
        codes = read_rows(Path(self.path), "frames", self._frames, row, row + 1, self.owners[i])
        if self.checksums is not None and self.checksums[1][i] and row_checksums(codes, codes.dtype)[0] != (
                self.checksums[0][i]):
            problem = "its frames row differs from the checksum in its record (a chunk moved from elsewhere or missing)"
            raise DatasetError(damage_message(Path(self.path), self.owners[i], problem))
        frames = decode_frames(codes[0], self.encoding)
        probe = {name: values[i] for name, values in self.probe.items()}
        return torch.from_numpy(frames), probe, torch.tensor(self.labels[i], dtype=torch.int64)


__all__ = ["TorchTactileDataset"]
