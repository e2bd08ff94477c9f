"""Adversarial checks of write_model_file's byte order: arrays of any byte order, contiguity and shape save, load
with their values, and give the file their little-endian twins give."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.modelfile import FORMAT_VERSION, read_model_file, write_model_file

DTYPES = ["<f8", ">f8", ">f4", ">f2", ">i8", ">i4", ">i2", ">u8", ">u4", ">u2", "|u1", "|i1", "|b1"]


def _values(dtype: str) -> np.ndarray:
    rng = np.random.default_rng(len(dtype) + sum(map(ord, dtype)))
    kind = np.dtype(dtype).kind
    if kind == "f":
        values = rng.normal(0, 1e3, (5, 4))
        values[0, :3] = -0.0, np.finfo(np.dtype(dtype)).max, np.finfo(np.dtype(dtype)).tiny
        return values.astype(dtype)
    if kind == "b":
        return (rng.random((5, 4)) < 0.5).astype(dtype)
    info = np.iinfo(np.dtype(dtype))
    values = rng.integers(info.min, info.max, (5, 4), endpoint=True, dtype=np.dtype(dtype).newbyteorder("="))
    values[0, :2] = info.min, info.max
    return values.astype(dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("layout", ["contiguous", "strided", "transposed", "scalar", "empty"])
def test_arrays_of_any_byte_order_load_with_their_values(tmp_path, dtype, layout):
    full = _values(dtype)
    value = {"contiguous": full, "strided": full[::2, 1::2], "transposed": full.T, "scalar": full[1, 1:2].reshape(()),
             "empty": full[:0]}[layout]
    assert value.dtype == np.dtype(dtype)
    path = write_model_file(tmp_path / "m.vtm", {"version": FORMAT_VERSION, "note": layout}, {"state": value})
    description, arrays = read_model_file(path)
    loaded = arrays["state"]
    assert description == {"version": FORMAT_VERSION, "note": layout}
    assert loaded.shape == value.shape
    assert loaded.dtype == np.dtype(dtype).newbyteorder("<")
    assert loaded.tolist() == value.tolist()  # Python numbers: independent of byte order
    # The little-endian C-ordered twin (converted by numpy, not by the writer) gives the same file.
    twin = value.astype(np.dtype(dtype).newbyteorder("<"), order="C")
    assert twin.shape == value.shape
    assert write_model_file(tmp_path / "twin.vtm", {"version": FORMAT_VERSION, "note": layout}, {"state": twin}).read_bytes() == path.read_bytes()


def test_mixed_byte_orders_in_one_file(tmp_path):
    arrays = {"a": _values(">f8"), "b": _values("<i4"), "c": _values(">u2")[::-1]}
    path = write_model_file(tmp_path / "m.vtm", {"version": FORMAT_VERSION}, arrays)
    _, loaded = read_model_file(path)
    assert sorted(loaded) == ["a", "b", "c"]
    for key, value in arrays.items():
        assert loaded[key].dtype.byteorder in "<=|" and loaded[key].tolist() == value.tolist()


def test_writing_leaves_the_callers_arrays_alone(tmp_path):
    big = _values(">f8")
    before = big.copy()
    write_model_file(tmp_path / "m.vtm", {"version": FORMAT_VERSION}, {"a": big})
    assert big.dtype == np.dtype(">f8") and big.tobytes() == before.tobytes()
