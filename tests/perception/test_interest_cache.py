"""The interest-point cache: keyed by what saliency reads, damaged entries ignored, known points served."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from perception.errors import SaliencyError
from perception.geometry import random_rotation
from perception.interest_cache import MAX_ENTRY_BYTES, InterestPointCache, KnownInterestPoints
from perception.shapes import make_object


@pytest.fixture
def mug():
    return make_object("mug", 0)


def test_round_trip_and_key_follows_the_mesh_not_its_name(mug, tmp_path):
    cache = InterestPointCache(tmp_path)
    points = mug.vertices[:10].copy()
    assert cache.get(mug, "multiview", 0, 10) is None
    cache.put(mug, "multiview", 0, points)
    np.testing.assert_array_equal(cache.get(mug, "multiview", 0, 10), points)
    renamed = dataclasses.replace(mug, name="another name", label="cup")
    np.testing.assert_array_equal(cache.get(renamed, "multiview", 0, 10), points)
    turned = dataclasses.replace(mug, vertices=mug.vertices @ random_rotation(3).T)
    assert cache.get(turned, "multiview", 0, 10) is None  # another pose is another mesh
    coloured = dataclasses.replace(mug, vertex_colors=np.full((mug.n_vertices, 3), 0.5))
    assert cache.get(coloured, "multiview", 0, 10) is None  # colours feed the colour channels
    assert cache.get(mug, "mesh", 0, 10) is None and cache.get(mug, "multiview", 1, 10) is None
    assert cache.get(mug, "multiview", 0, 9) is None


@pytest.mark.parametrize("damage", ["garbage", "shape", "nan", "large", "pickle"])
def test_damaged_entries_are_ignored(mug, tmp_path, damage):
    cache = InterestPointCache(tmp_path)
    cache.put(mug, "multiview", 0, mug.vertices[:10])
    (path,) = tmp_path.glob("*.npy")
    if damage == "garbage":
        path.write_bytes(b"\x93NUMPY not really")
    elif damage == "shape":
        np.save(path, np.zeros((9, 3)))
    elif damage == "nan":
        np.save(path, np.full((10, 3), np.nan))
    elif damage == "large":
        np.save(path, np.zeros((MAX_ENTRY_BYTES // 24 + 10, 3)))
    else:
        np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    assert cache.get(mug, "multiview", 0, 10) is None


def test_an_unwritable_cache_only_warns(mug, tmp_path, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    InterestPointCache(blocker / "cache").put(mug, "multiview", 0, mug.vertices[:10])
    assert "could not cache" in caplog.text


def test_known_points_serve_sampling_and_refuse_more_than_known(mug):
    known = KnownInterestPoints(mug, "multiview", mug.vertices[:10])
    np.testing.assert_array_equal(known.interest_points(4), mug.vertices[:4])
    with pytest.raises(SaliencyError, match="10 interest points are known, 11 asked for"):
        known.interest_points(11)


def test_key_covers_everything_saliency_reads_and_the_code(mug, monkeypatch):
    from perception import interest_cache
    from perception.geometry import CENTERINGS

    cache = InterestPointCache("unused")
    key = cache.key(mug, "multiview", 0, 10)
    moved = mug.transform.copy()
    moved[0, 3] += 1.0
    other = next(c for c in CENTERINGS if c != mug.centering)
    for changed in (dataclasses.replace(mug, transform=moved), dataclasses.replace(mug, triangles=mug.triangles[:, ::-1]),
                    dataclasses.replace(mug, centering=other)):
        assert cache.key(changed, "multiview", 0, 10) != key
    assert cache.key(mug, "multiview", 0, 9) != key
    monkeypatch.setattr(interest_cache, "code_version", lambda: "other code")
    assert cache.key(mug, "multiview", 0, 10) != key


@pytest.mark.parametrize("library", ["numpy", "scipy", "open3d", "pymeshlab"])
def test_another_library_version_is_another_key(monkeypatch, library):
    """numpy, SciPy, Open3D (renders the views, casts the rays) and pymeshlab shape the interest points: points cached
    under another version of any of them are computed again."""
    from perception import interest_cache, runtime

    real = runtime.version
    interest_cache.code_version.cache_clear()
    try:
        before = interest_cache.code_version()
        monkeypatch.setattr(runtime, "version", lambda name: "0.0.1" if name == library else real(name))
        interest_cache.code_version.cache_clear()
        assert interest_cache.code_version() != before
        monkeypatch.setattr(runtime, "version", real)
        interest_cache.code_version.cache_clear()
        assert interest_cache.code_version() == before
    finally:
        interest_cache.code_version.cache_clear()


def test_every_keyed_library_is_installed():
    """A misspelt distribution name would read "not installed" forever and key nothing."""
    from perception.interest_cache import SALIENCY_LIBRARIES
    from perception.runtime import versions

    assert "not installed" not in versions(*SALIENCY_LIBRARIES).values()


class _Boom:
    def __reduce__(self):
        return (pytest.fail, ("a cache entry ran code",))


@pytest.mark.parametrize("damage", ["float32", "pickle_right_shape", "fifo", "huge_header", "oversized"])
def test_entries_are_checked_before_anything_is_read(mug, tmp_path, monkeypatch, damage):
    """A FIFO is not waited on, a pickled array never unpickled, a header promising a huge array never
    allocated, an oversized file never parsed."""
    import os

    cache = InterestPointCache(tmp_path)
    cache.put(mug, "multiview", 0, mug.vertices[:10])
    (path,) = tmp_path.glob("*.npy")
    if damage == "float32":
        np.save(path, mug.vertices[:10].astype(np.float32))
    elif damage == "pickle_right_shape":
        a = np.empty((10, 3), dtype=object)
        a[:] = _Boom()
        np.save(path, a, allow_pickle=True)
    elif damage == "fifo":
        path.unlink()
        os.mkfifo(path)
    elif damage == "huge_header":
        header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000, 3), }"
        pad = 64 - (10 + len(header) + 1) % 64
        path.write_bytes(b"\x93NUMPY\x01\x00" + (len(header) + pad + 1).to_bytes(2, "little") + header + b" " * pad + b"\n")
    else:
        path.write_bytes(b"\x93NUMPY" + b"\0" * MAX_ENTRY_BYTES)
    monkeypatch.setattr(np.lib.format, "read_array", lambda *a, **k: pytest.fail("an unchecked entry was read"))
    assert cache.get(mug, "multiview", 0, 10) is None


def test_known_points_are_copies_and_a_failed_write_leaves_no_entry(mug, tmp_path, monkeypatch):
    known = KnownInterestPoints(mug, "multiview", mug.vertices[:10].copy())
    known.interest_points(4)[:] = 0.0
    np.testing.assert_array_equal(known.points[:4], mug.vertices[:4])

    def half(f, a, **k):
        f.write(b"\x93NUMPY")
        raise OSError("disk full")

    monkeypatch.setattr(np, "save", half)
    InterestPointCache(tmp_path).put(mug, "multiview", 0, mug.vertices[:10])
    assert not list(tmp_path.glob("*"))
