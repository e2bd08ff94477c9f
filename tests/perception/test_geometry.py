"""Loading, validation, repair, scaling and dataset listing, against hand-made files with known content."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from perception.errors import (
    DatasetError,
    InvalidArgumentError,
    InvalidMeshError,
    MeshLoadError,
    VisuotactileError,
)
from perception.geometry import ObjectModel, list_collection, load_object, normalize
from perception.primitives import sphere

# A unit cube as quads: 8 vertices, 6 faces -> 12 triangles after triangulation.
CUBE_OFF = """OFF
# a comment line
8 6 0
0 0 0
1 0 0
1 1 0
0 1 0
0 0 1
1 0 1
1 1 1
0 1 1
4 0 3 2 1
4 4 5 6 7
4 0 1 5 4
4 1 2 6 5
4 2 3 7 6
4 3 0 4 7
"""


def write(tmp_path, name: str, content: str | bytes):
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return path


def signed_volume(model: ObjectModel) -> float:
    v0, v1, v2 = (model.vertices[model.triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0)


def test_off_polygon_faces_are_triangulated_and_scaled(tmp_path):
    model = load_object(write(tmp_path, "cube.off", CUBE_OFF), label="box")
    assert model.n_vertices == 8 and model.n_triangles == 12
    assert model.is_watertight
    assert model.diagonal == pytest.approx(150.0)
    np.testing.assert_allclose(model.center, 0.0, atol=1e-12)
    # A cube of side s has diagonal s * sqrt(3): side 150 / sqrt(3), volume side ** 3, outward winding.
    side = 150.0 / np.sqrt(3.0)
    assert signed_volume(model) == pytest.approx(side**3)
    assert model.label == "box" and model.name == "cube"
    # The transform maps source coordinates onto the model's.
    source = np.array([[1.0, 1.0, 1.0, 1.0]])
    np.testing.assert_allclose((model.transform @ source.T).T[0, :3], [side / 2] * 3)


def test_glued_off_header_loads(tmp_path):
    glued = CUBE_OFF.replace("OFF\n# a comment line\n8 6 0", "OFF8 6 0")
    assert load_object(write(tmp_path, "glued.off", glued)).n_triangles == 12


def test_size_none_keeps_source_coordinates(tmp_path):
    model = load_object(write(tmp_path, "cube.off", CUBE_OFF), size_mm=None)
    np.testing.assert_allclose(model.bounds, [[0, 0, 0], [1, 1, 1]])


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl"])
def test_open3d_formats_round_trip(tmp_path, suffix):
    mesh = sphere(20.0, 2).to_open3d()
    mesh.compute_triangle_normals()  # the STL writer needs them
    path = tmp_path / f"ball{suffix}"
    assert o3d.io.write_triangle_mesh(str(path), mesh)
    model = load_object(path, size_mm=None)
    # STL stores triangle soup; repair merges the duplicated corners back to the 162 icosphere vertices.
    assert model.n_vertices == 162 and model.n_triangles == 320
    np.testing.assert_allclose(np.linalg.norm(model.vertices, axis=1), 20.0, rtol=1e-5)


def test_open3d_mesh_input():
    model = load_object(sphere(10.0, 1).to_open3d(), label="ball")
    assert model.name == "open3d-mesh" and model.label == "ball" and model.n_vertices == 42


def test_repair_merges_duplicates_and_drops_degenerate_faces():
    # Two triangles of a square with the shared corners duplicated, a zero-area face and an unused vertex.
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 0], [1, 1, 0], [0, 1, 0], [5, 5, 5]], float)
    t = np.array([[0, 1, 2], [3, 4, 5], [0, 0, 1]])
    model = load_object(o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t)),
                        size_mm=None)
    assert model.n_vertices == 4 and model.n_triangles == 2
    assert model.triangle_areas.sum() == pytest.approx(1.0)
    # Indices still consistent: every triangle has non-zero area.
    assert (model.triangle_areas > 0).all()


def test_vertex_colors_survive_repair(tmp_path):
    coff = "COFF\n3 1 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n3 0 1 2\n"
    model = load_object(write(tmp_path, "tri.off", coff))
    assert model.has_colors
    np.testing.assert_allclose(np.sort(model.vertex_colors.sum(axis=1)), [1.0, 1.0, 1.0])


def test_off_lines_read_the_same_whatever_the_parser_path(tmp_path):
    """Bare ``x y z`` / ``3 a b c`` lines are parsed in one call; a file with a face colour, a quad, an extra vertex
    token or exponents takes the line-by-line path. Hand-written expected arrays, and both paths agree."""
    from perception.meshio import read_off

    expected_v = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [1.5, 2.0, 0.0], [0.0, 2.0, 1e-3]])
    expected_t = np.array([[0, 1, 2], [0, 2, 3]])
    bare = "OFF\n4 2 0\n0 0 0\n1.5 0 0\n1.5 2 0\n0 2 1e-3\n3 0 1 2\n3 0 2 3\n"
    variants = {
        "bare": bare,
        "face colour": bare.replace("3 0 2 3\n", "3 0 2 3 0.5 0.5 0.5\n"),
        "quad": "OFF\n4 1 0\n0 0 0\n1.5 0 0\n1.5 2 0\n0 2 1e-3\n4 0 1 2 3\n",
        "vertex token": bare.replace("1.5 2 0\n", "1.5 2 0 7\n"),
        "comments, +signs, 0-padding": bare.replace("3 0 1 2\n", "+3 00 1 2  # first\n").replace("OFF\n", "OFF # x\n"),
    }
    for name, text in variants.items():
        raw = read_off(write(tmp_path, "m.off", text))
        np.testing.assert_array_equal(raw.vertices, expected_v, err_msg=name)
        np.testing.assert_array_equal(raw.triangles, expected_t, err_msg=name)
        assert raw.triangles.dtype == np.int64 and raw.vertices.dtype == np.float64 and raw.vertex_colors is None
    with pytest.raises(MeshLoadError, match="bad OFF face line"):
        read_off(write(tmp_path, "m.off", bare.replace("3 0 2 3\n", "2 0 2 3\n")))
    with pytest.raises(MeshLoadError, match="malformed"):
        read_off(write(tmp_path, "m.off", bare.replace("3 0 2 3\n", "3 0 2 x\n")))
    with pytest.raises(MeshLoadError, match="malformed"):
        read_off(write(tmp_path, "m.off", bare.replace("3 0 2 3\n", "3 0 2 99999999999999999999\n")))


# --------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("name", "content", "error", "words"),
    [
        ("empty.off", b"", MeshLoadError, "empty"),
        ("empty.ply", b"", MeshLoadError, "empty"),
        ("noise.off", bytes(range(256)) * 8, MeshLoadError, "ASCII"),
        ("noise.ply", bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8)), MeshLoadError, "PLY"),
        ("noise.obj", bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8)), MeshLoadError, "triangles"),
        ("nan.off", "OFF\n3 1 0\n0 0 0\nnan 1 0\n0 1 0\n3 0 1 2\n", InvalidMeshError, "NaN"),
        ("range.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", InvalidMeshError, "out of range"),
        ("negative.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n", InvalidMeshError, "out of range"),
        ("huge.off", "OFF\n100000000 1 0\n0 0 0\n", MeshLoadError, "more than"),
        ("short.off", "OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n", MeshLoadError, "truncated"),
        ("header.off", "PLY\n3 1 0\n", MeshLoadError, "OFF header"),
        ("flat.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n2 0 0\n3 0 1 2\n", InvalidMeshError, "non-zero area"),
        ("huge.ply", "ply\nformat ascii 1.0\nelement vertex 999999999\nproperty float x\nend_header\n",
         MeshLoadError, "declares"),
        ("mesh.xyz", "0 0 0\n", MeshLoadError, "unknown mesh type"),
        ("nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", InvalidMeshError, "NaN"),
        ("range.ply", ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
         "0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n"), InvalidMeshError, "out of range"),
    ],
)
def test_bad_files_raise_specific_errors_naming_the_file(tmp_path, name, content, error, words):
    path = write(tmp_path, name, content)
    with pytest.raises(error) as info:
        load_object(path)
    assert str(path) in str(info.value)
    assert words in str(info.value)
    assert isinstance(info.value, VisuotactileError)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(MeshLoadError, match="no such file"):
        load_object(tmp_path / "nope.off")
    (tmp_path / "dir.off").mkdir()
    with pytest.raises(MeshLoadError, match="directory"):
        load_object(tmp_path / "dir.off")


@pytest.mark.parametrize("suffix", [".off", ".obj", ".ply", ".stl"])
def test_a_file_above_the_size_limit_is_refused_unread(tmp_path, monkeypatch, suffix):
    """A sparse 3 MB file over a 2 MB limit: refused from its size (the message names the file, the limit and the
    variable), before any byte is read."""
    monkeypatch.setenv("VISUOTACTILE_MAX_FILE_MB", "2")
    path = tmp_path / f"big{suffix}"
    with open(path, "wb") as f:
        f.truncate(3 * 2**20)
    real_open = open
    with monkeypatch.context() as unread, pytest.raises(MeshLoadError, match="3 MB, above the limit of 2 MB per mesh "
                                                                            "file") as info:
        unread.setattr("builtins.open", lambda *a, **k: pytest.fail(f"opened {a[0]}") if str(a[0]) == str(path)
                       else real_open(*a, **k))
        unread.setattr(type(path), "read_bytes", lambda self: pytest.fail(f"read {self}"))
        load_object(path)
    assert "big" in str(info.value) and "VISUOTACTILE_MAX_FILE_MB" in str(info.value)
    monkeypatch.setenv("VISUOTACTILE_MAX_FILE_MB", "4")  # within the limit: past the size check, to the parser
    with pytest.raises(MeshLoadError) as info:
        load_object(path)
    assert "limit" not in str(info.value)


@pytest.mark.parametrize(
    ("vertices", "triangles", "words"),
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "non-empty"),
        (np.zeros((3, 2)), [[0, 1, 2]], "(V, 3)"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1]], "(F, 3)"),
        ([[0, 0, 0], [1, 0, 0], [0, np.inf, 0]], [[0, 1, 2]], "Inf"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], "out of range"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 1.5]], "integers"),
    ],
)
def test_object_model_validates_arrays(vertices, triangles, words):
    with pytest.raises(InvalidMeshError, match=None) as info:
        ObjectModel(np.asarray(vertices, float), np.asarray(triangles), name="thing")
    assert "thing" in str(info.value) and words in str(info.value)


def test_normalize_rejects_point_and_bad_size():
    with pytest.raises(InvalidMeshError, match="zero extent"):
        normalize(np.ones((4, 3)))
    with pytest.raises(InvalidArgumentError, match="size_mm"):
        normalize(np.eye(3), size_mm=-1.0)


# ------------------------------------------------------------------------------- mesh collection
def test_list_collection_lists_class_folders(tmp_path):
    for cls, files in {"Cup": ["b.off", "a.off"], "Box": ["x.obj"]}.items():
        (tmp_path / cls).mkdir()
        for f in files:
            write(tmp_path / cls, f, CUBE_OFF)
    (tmp_path / "Cup" / "notes.txt").write_text("ignored")
    (tmp_path / ".hidden").mkdir()
    items = list_collection(tmp_path)
    assert [(p.name, label) for p, label in items] == [("x.obj", "Box"), ("a.off", "Cup"), ("b.off", "Cup")]


def test_list_collection_errors(tmp_path):
    with pytest.raises(DatasetError, match="not a folder"):
        list_collection(tmp_path / "missing")
    with pytest.raises(DatasetError, match="no class subfolders") as info:
        list_collection(tmp_path)
    assert str(tmp_path) in str(info.value)
    (tmp_path / "Empty").mkdir()
    with pytest.raises(DatasetError, match="'Empty' holds no mesh files"):
        list_collection(tmp_path)
    write(tmp_path, "loose.off", CUBE_OFF)
    with pytest.raises(DatasetError, match="directly in the root"):
        list_collection(tmp_path)


def test_the_former_name_is_the_same_function():
    import perception
    from perception import geometry

    assert geometry.load_dataset is list_collection and perception.load_dataset is perception.list_collection


def test_the_geometry_module_names_only_the_loaders_that_moved():
    """perception.geometry still names the loaders of perception.loading (the same functions), and nothing else
    it lacks: an unknown name is an AttributeError (hasattr false, ``from ... import`` an ImportError)."""
    from perception import geometry, loading

    assert geometry.load_object is loading.load_object and geometry.list_collection is loading.list_collection
    assert not hasattr(geometry, "load_everything")
    with pytest.raises(AttributeError, match="load_everything"):
        geometry.load_everything  # noqa: B018
    with pytest.raises(ImportError):
        from perception.geometry import load_everything  # noqa: F401


# ------------------------------------------------------------------------------------- derived data
def test_cached_properties_and_open3d_copy():
    model = sphere(30.0, 3)
    assert model.scene is model.scene
    assert model.vertex_normals is model.vertex_normals
    mesh = model.to_open3d()
    assert len(mesh.vertices) == model.n_vertices and mesh.has_vertex_normals()
    # Closest point of an outside query on a sphere: along the ray from the centre, at distance |q| - R.
    closest, dist = model.closest_points(np.array([[0.0, 0.0, 100.0]]))
    assert dist[0] == pytest.approx(70.0, abs=0.1)
    assert closest[0, 2] == pytest.approx(30.0, abs=0.1)


_V4 = "0 0 0\n1 0 0\n1 1 0\n0 1 0\n"


@pytest.mark.parametrize("faces", ["3 0 1 2 3\n0 2 3\n", "3 0 1 2 3\n1 2 3\n", "3 0 1\n3 3 0 2 3\n",
                                   "3 0 1\n2 3 0 2 3\n"])
def test_off_face_lines_are_checked_line_by_line_not_by_their_total(tmp_path, faces):
    """A short face line beside a long one holds as many tokens as two triangles: still a bad face line."""
    from perception.meshio import read_off

    with pytest.raises(MeshLoadError, match="bad OFF face line"):
        read_off(write(tmp_path, "m.off", "OFF\n4 2 0\n" + _V4 + faces))


@pytest.mark.parametrize("vertices", ["0 0\n1 0 0 7\n1 1 0\n0 1 0\n", "0 0 0 1\n0 0\n1 1 0\n0 1 0\n",
                                      "0 0\n0 0\n0 0 0 0 0\n0 1 0\n"])
def test_off_vertex_lines_are_checked_line_by_line_not_by_their_total(tmp_path, vertices):
    from perception.meshio import read_off

    with pytest.raises(MeshLoadError, match="malformed|3 coordinates"):
        read_off(write(tmp_path, "m.off", f"OFF\n{vertices.count(chr(10))} 1 0\n" + vertices + "3 0 1 2\n"))


def test_off_face_count_beyond_int64_is_a_bad_face_line(tmp_path):
    from perception.meshio import read_off

    with pytest.raises(MeshLoadError, match="bad OFF face line"):
        read_off(write(tmp_path, "m.off", "OFF\n4 2 0\n" + _V4 + "3 0 1 2\n9223372036854775808 0 2 3\n"))


class _NoSplit(str):
    """A line whose own split() fails: only the one-call path (which splits the joined text) reads it."""

    def split(self, *args, **kwargs):
        raise AssertionError("bare lines took the line-by-line path")


def test_bare_off_lines_take_the_one_call_path():
    from pathlib import Path

    from perception.meshio import _off_triangles, _off_vertices

    np.testing.assert_array_equal(_off_triangles(Path("m.off"), [_NoSplit("3 0 1 2"), _NoSplit("3 0 2 3")]),
                                  [[0, 1, 2], [0, 2, 3]])
    vertices, colors = _off_vertices([_NoSplit("0 0 0"), _NoSplit("1.5 2 1e-3")], False)
    np.testing.assert_array_equal(vertices, [[0, 0, 0], [1.5, 2, 1e-3]])
    assert colors is None


def test_off_triangles_are_contiguous_int64_with_big_indices(tmp_path):
    """Indices up to int64 are read as the old parser read them (out-of-range ones are refused by the model checks)."""
    from perception.meshio import read_off

    raw = read_off(write(tmp_path, "m.off", "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 1099511627776\n"))
    assert raw.triangles.dtype == np.int64 and raw.triangles.flags.c_contiguous
    np.testing.assert_array_equal(raw.triangles, [[0, 1, 2], [0, 1, 2**40]])


def test_coff_colours_already_in_unit_range_are_kept(tmp_path):
    from perception.meshio import read_off

    raw = read_off(write(tmp_path, "m.off", "COFF\n3 1 0\n0 0 0 1 0 0\n1 0 0 0 1 0\n0 1 0 0 0 1\n3 0 1 2\n"))
    np.testing.assert_array_equal(raw.vertex_colors, np.eye(3))
