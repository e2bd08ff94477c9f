"""The procedural object catalogue: closed, outward, scaled, seeded meshes, checked against known answers."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from perception import shapes
from perception.errors import DatasetError, InvalidArgumentError, VisuotactileError
from perception.geometry import ObjectModel, surface_centroid
from perception.shapes import CLASSES, catalogue_figure, make_dataset, make_object

N_SEEDS = 20
REPO = Path(__file__).resolve().parents[2]

# Topology by design: a handle (mug), a hole (ring) or a tube open at both ends (funnel) make genus 1.
GENUS = {"funnel": 1, "mug": 1, "ring": 1}


@pytest.fixture(scope="module")
def catalogue() -> dict[str, list[ObjectModel]]:
    """Seeds 0 .. N_SEEDS - 1 of every class, built once for the module."""
    return {c: [make_object(c, s) for s in range(N_SEEDS)] for c in CLASSES}


def signed_volume(model: ObjectModel) -> float:
    v0, v1, v2 = (model.vertices[model.triangles[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->", v0, np.cross(v1, v2)) / 6.0)


def digest(model: ObjectModel) -> str:
    return hashlib.sha256(model.vertices.tobytes() + model.triangles.tobytes()).hexdigest()


def undirected_edges(model: ObjectModel) -> np.ndarray:
    """(E, 2) unique edges; same as ``model.edges``, through 1-D keys (several times faster)."""
    f = model.triangles.astype(np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    keys = np.unique(e[:, 0] * model.n_vertices + e[:, 1])
    return np.stack([keys // model.n_vertices, keys % model.n_vertices], axis=1)


def closed_and_oriented(model: ObjectModel) -> bool:
    """``ObjectModel.is_watertight``'s definition (every edge in two triangles, every directed edge once)
    through 1-D keys: ten times faster, so that all instances can be checked within the time budget."""
    f = model.triangles.astype(np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = model.n_vertices
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    return bool(np.all(counts == 2)) and len(np.unique(directed[:, 0] * n + directed[:, 1])) == len(directed)


def euler_characteristic(model: ObjectModel) -> int:
    return model.n_vertices - len(undirected_edges(model)) + model.n_triangles


def edge_lengths(model: ObjectModel) -> np.ndarray:
    e = undirected_edges(model)
    return np.linalg.norm(model.vertices[e[:, 0]] - model.vertices[e[:, 1]], axis=1)


def dihedral_deg(model: ObjectModel) -> np.ndarray:
    """Angle between the normals of the two triangles at every edge (closed meshes)."""
    f = model.triangles
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(len(f)), 3)
    key = np.sort(directed, axis=1)
    pair = owner[np.lexsort((key[:, 1], key[:, 0]))]
    n = model.triangle_normals
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n[pair[0::2]], n[pair[1::2]]), -1, 1)))


def shape_descriptor(model: ObjectModel) -> np.ndarray:
    """Pose-invariant numbers of a closed surface: area, volume, and the sorted principal second moments of
    the surface (area-weighted triangle centroids), all at the catalogue's common 150 mm size."""
    centroids = model.vertices[model.triangles].mean(axis=1)
    weights = model.triangle_areas / model.triangle_areas.sum()
    centred = centroids - weights @ centroids
    moments = np.linalg.eigvalsh((centred * weights[:, None]).T @ centred)
    return np.concatenate([[model.triangle_areas.sum(), signed_volume(model)], np.sort(moments)])


def test_at_least_eight_geometrically_distinct_classes(catalogue):
    # Distinct by shape, not by name: every two classes' first instances differ by more than 5 % in at
    # least one pose-invariant number (two builders making the same solid would fail this).
    names = list(catalogue)
    descriptors = np.array([shape_descriptor(catalogue[c][0]) for c in names])
    assert len(names) >= 8
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            relative = np.abs(descriptors[i] - descriptors[j]) / np.maximum(np.abs(descriptors[i]), np.abs(descriptors[j]))
            assert relative.max() > 0.05, (names[i], names[j], relative)


def test_every_instance_is_closed_outward_centred_and_scaled(catalogue):
    for class_name, models in catalogue.items():
        for seed, model in enumerate(models):
            assert model.name == f"{class_name}/{seed}"
            assert model.label == class_name
            assert closed_and_oriented(model), model.name
            assert signed_volume(model) > 0, model.name
            # the pose-free size (enclosing-sphere diameter about the surface centroid), checked by hand
            centroid = surface_centroid(model.vertices, model.triangles)
            assert 2 * np.linalg.norm(model.vertices - centroid, axis=1).max() == pytest.approx(150.0, rel=1e-9)
            np.testing.assert_allclose(centroid, 0.0, atol=1e-9 * 150)
            assert np.isfinite(model.vertices).all()


def test_is_watertight_agrees_with_trimesh(catalogue):
    trimesh = pytest.importorskip("trimesh")

    def peer(model: ObjectModel) -> bool:  # every edge in exactly two faces, and consistent winding
        mesh = trimesh.Trimesh(model.vertices, model.triangles, process=False)
        return bool(mesh.is_watertight and mesh.is_winding_consistent)

    model = catalogue["mug"][0]
    t = model.triangles
    cases = [models[0] for models in catalogue.values()] + [
        ObjectModel(model.vertices, t[1:], name="holed"),
        ObjectModel(model.vertices, np.vstack([t[:1, ::-1], t[1:]]), name="one face flipped"),
        ObjectModel(model.vertices, np.vstack([t, t[:1, ::-1]]), name="an edge in three faces"),
    ]
    verdicts = {m.name: (m.is_watertight, peer(m)) for m in cases}
    assert all(ours == theirs for ours, theirs in verdicts.values()), verdicts
    assert sum(ours for ours, _ in verdicts.values()) == len(catalogue)  # the catalogue yes, the rest no


def test_topology_matches_the_design(catalogue):
    """Euler characteristic V - E + F = 2 - 2 genus: one hole for ring, mug handle, funnel tube."""
    for class_name, models in catalogue.items():
        for model in models:
            assert euler_characteristic(model) == 2 - 2 * GENUS.get(class_name, 0), model.name


def _open3d_agrees(model: ObjectModel) -> None:
    mesh = model.to_open3d()
    assert mesh.is_watertight(), model.name  # edge- and vertex-manifold, and no self-intersection
    assert mesh.get_volume() == pytest.approx(signed_volume(model), rel=1e-9)


# The classes built with 3D booleans (handles, heads, lids) and with 2D unions (stem into bowl).
JOINED = ("box", "hammer", "mug", "spoon", "wineglass")


@pytest.mark.parametrize("class_name", JOINED)
def test_open3d_finds_joined_parts_closed_without_self_intersections(class_name):
    """A peer library: Open3D's watertightness includes a self-intersection test; its volume matches ours."""
    _open3d_agrees(make_object(class_name, 0))


@pytest.mark.slow
@pytest.mark.parametrize("class_name", CLASSES)
def test_open3d_finds_every_class_closed_without_self_intersections(class_name):
    for seed in range(5):
        _open3d_agrees(make_object(class_name, seed))


def test_instances_of_a_class_differ(catalogue):
    for class_name, models in catalogue.items():
        assert len({digest(m) for m in models}) == N_SEEDS, class_name
        # Not only the tessellation: the shapes themselves differ (volume at the common 150 mm size).
        volumes = np.sort([signed_volume(m) for m in models])
        assert np.all(np.diff(volumes) > 1e-6 * volumes[-1]), class_name


def test_same_seed_gives_identical_bytes(catalogue):
    for class_name in CLASSES:
        again = make_object(class_name, 3)
        assert again.vertices.tobytes() == catalogue[class_name][3].vertices.tobytes()
        assert again.triangles.tobytes() == catalogue[class_name][3].triangles.tobytes()


def test_same_seed_gives_identical_bytes_in_another_process(catalogue):
    code = (
        "import hashlib; from perception.shapes import make_object; "
        "print(' '.join(hashlib.sha256(m.vertices.tobytes() + m.triangles.tobytes()).hexdigest() "
        "for m in (make_object('mug', 5), make_object('box', 6), make_object('spoon', 7))))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    here = [digest(catalogue["mug"][5]), digest(catalogue["box"][6]), digest(catalogue["spoon"][7])]
    assert out.stdout.split() == here


def test_generator_seed():
    a = make_object("bottle", np.random.default_rng(11))
    b = make_object("bottle", np.random.default_rng(11))
    assert a.name == "bottle/rng"
    assert a.vertices.tobytes() == b.vertices.tobytes()
    rng = np.random.default_rng(11)
    first, second = make_object("bottle", rng), make_object("bottle", rng)
    assert first.vertices.tobytes() != second.vertices.tobytes()  # the generator moved on


def test_unknown_class_raises_and_lists_the_classes():
    with pytest.raises(DatasetError) as info:
        make_object("teapot", 0)
    assert "teapot" in str(info.value)
    assert all(c in str(info.value) for c in CLASSES)
    assert isinstance(info.value, VisuotactileError)


@pytest.mark.parametrize("seed", [-1, 1.5, True, "3", None])
def test_bad_seed_raises(seed):
    with pytest.raises(DatasetError, match="seed"):
        make_object("mug", seed)


@pytest.mark.parametrize("size_mm", [0.0, -10.0, float("nan"), float("inf")])
def test_bad_size_raises(size_mm):
    with pytest.raises(InvalidArgumentError, match="size_mm"):
        make_object("mug", 0, size_mm=size_mm)


def test_size_mm_scales_the_whole_mesh(catalogue):
    """Resolution is relative to the object: twice the size is exactly the same mesh, twice as large."""
    big = make_object("hammer", 4, size_mm=300.0)
    small = catalogue["hammer"][4]
    assert big.size == pytest.approx(300.0, rel=1e-9)
    np.testing.assert_array_equal(big.triangles, small.triangles)
    np.testing.assert_allclose(big.vertices, 2 * small.vertices, rtol=0, atol=1e-12 * 300)


def test_size_alone_does_not_give_the_class_away(catalogue):
    """Over 10 instances per class the size is one number, and no class stands apart by its bounding-box
    volume: each class's range overlaps another class's range. (The longest side is not checked: with the
    pose-free size, the enclosing-sphere diameter, a flat ring's diameter *is* its size, 148-150 mm against
    96-143 mm for the other classes; that is its shape, which touch is meant to find.)"""
    first = {c: models[:10] for c, models in catalogue.items()}
    sizes = np.array([m.size for models in first.values() for m in models])
    np.testing.assert_allclose(sizes, 150.0, rtol=1e-9)
    extents = {c: np.array([np.ptp(m.vertices, axis=0) for m in models]) for c, models in first.items()}
    for measure in (lambda e: e.prod(axis=1),):
        ranges = {c: (measure(e).min(), measure(e).max()) for c, e in extents.items()}
        for c, (lo, hi) in ranges.items():
            others = [d for d, (lo2, hi2) in ranges.items() if d != c and lo2 <= hi and lo <= hi2]
            assert others, f"{c} is told apart by size alone: {ranges}"


def test_resolution_suits_a_20_mm_pad(catalogue):
    """2k-15k triangles, edges of about 2-4 mm on a 150 mm object, and smooth where the design is smooth:
    most neighbouring facets within 15 degrees (the construction's step; quad diagonals and small fillets
    reach about 21-25 degrees)."""
    for class_name, models in catalogue.items():
        for model in models:
            length = edge_lengths(model)
            assert 2000 <= model.n_triangles <= 15000, model.name
            assert 1.5 <= np.median(length) <= 4.5, model.name
            assert length.max() <= 7.0, model.name
        angles = np.concatenate([dihedral_deg(m) for m in models[:5]])
        assert np.median(angles) <= 5.0, class_name
        assert np.percentile(angles, 90) <= 25.0, class_name


def test_lathe_of_a_rectangle_is_a_prism_inside_the_cylinder():
    """Known answer: the surface of revolution of a rectangle is the cylinder; its vertices lie on it and
    the volume is the inscribed prism's, between the polygon with the fewest rings' sides and the circle."""
    radius, height, edge = 30.0, 80.0, 3.0
    solid = shapes._revolve(np.array([[0, 0], [radius, 0], [radius, height], [0, height]]), edge)
    model = _as_model(solid)
    assert model.is_watertight
    r = np.hypot(model.vertices[:, 0], model.vertices[:, 1])
    side = (model.vertices[:, 2] > 1e-9) & (model.vertices[:, 2] < height - 1e-9)
    np.testing.assert_allclose(r[side], radius, rtol=1e-12)
    n = max(24, int(np.ceil(2 * np.pi * radius / edge)))  # at least this many sides
    exact = np.pi * radius**2 * height
    assert exact * np.sin(2 * np.pi / n) / (2 * np.pi / n) <= signed_volume(model) < exact


def test_lathe_of_a_circle_is_a_torus_by_pappus():
    """Known answer: the volume of a torus is 2 pi^2 R r^2; facets at most 15 degrees apart in both
    directions keep an inscribed mesh within (sin 15 / (pi / 12))^2 of it."""
    major, minor, edge = 40.0, 12.0, 3.0
    t = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    section = np.stack([major + minor * np.cos(t), minor * np.sin(t)], axis=1)
    model = _as_model(shapes._revolve(section, edge, closed=True))
    assert model.is_watertight
    assert euler_characteristic(model) == 0  # genus 1
    exact = 2 * np.pi**2 * major * minor**2
    factor = (np.sin(np.radians(15)) / np.radians(15)) ** 2
    assert exact * factor <= signed_volume(model) < exact

    # Vertices on the torus; facet centres off it by no more than the two chord sagittas: 15 degree steps
    # round the section, chords of at most ``edge`` round the axis.
    def off_torus(p):
        return np.abs(np.hypot(np.hypot(p[:, 0], p[:, 1]) - major, p[:, 2]) - minor)

    assert off_torus(model.vertices).max() < 1e-9
    sagitta = minor * (1 - np.cos(np.radians(7.5))) + edge**2 / (8 * (major - minor))
    assert off_torus(model.vertices[model.triangles].mean(axis=1)).max() <= sagitta


def test_rounded_box_volume_is_the_minkowski_sum():
    """Known answer: a box rounded by r is the inner box grown by a ball of radius r,
    V = abc + 2r(ab + bc + ca) + pi r^2 (a + b + c) + 4/3 pi r^3 (a, b, c the inner sides); the mesh is
    inscribed (its vertices lie on the convex surface), so it is slightly smaller."""
    lo, hi, radius = np.array([-40.0, -25.0, -15.0]), np.array([40.0, 25.0, 15.0]), 6.0
    model = _as_model(shapes._rounded_box(lo, hi, radius, 3.0))
    assert model.is_watertight
    a, b, c = hi - lo - 2 * radius
    exact = a * b * c + 2 * radius * (a * b + b * c + c * a) + np.pi * radius**2 * (a + b + c)
    exact += 4 / 3 * np.pi * radius**3
    assert exact * 0.995 <= signed_volume(model) < exact
    np.testing.assert_allclose(np.ptp(model.vertices, axis=0), hi - lo, rtol=1e-12)


def test_make_dataset_rebuilds_each_object_from_its_name():
    objects = make_dataset(2, seed=5, classes=("ring", "box"))
    assert [m.name for m in objects] == ["ring/5", "ring/6", "box/5", "box/6"]
    for m in objects:
        class_name, seed = m.name.split("/")
        assert m.vertices.tobytes() == make_object(class_name, int(seed)).vertices.tobytes()
    assert make_dataset(0) == []
    with pytest.raises(InvalidArgumentError):
        make_dataset(-1)
    with pytest.raises(DatasetError, match="teapot"):
        make_dataset(1, classes=("teapot",))


def test_catalogue_figure_writes_a_png(tmp_path):
    import matplotlib.image

    path = catalogue_figure(tmp_path / "sheet" / "catalogue.png", seed=0, pixels=48)
    assert path == tmp_path / "sheet" / "catalogue.png"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    assert np.unique(image[..., :3].reshape(-1, 3), axis=0).shape[0] > 10  # shaded objects, not a blank page
    assert list(tmp_path.joinpath("sheet").iterdir()) == [path]  # no temporary file left behind


@pytest.mark.slow
def test_many_seeds_stay_closed_and_outward():
    for class_name in CLASSES:
        for seed in range(N_SEEDS, 200):
            model = make_object(class_name, seed)
            assert closed_and_oriented(model), model.name
            assert signed_volume(model) > 0, model.name
            assert euler_characteristic(model) == 2 - 2 * GENUS.get(class_name, 0), model.name


def _as_model(solid) -> ObjectModel:
    mesh = solid.to_mesh64()
    return ObjectModel(np.asarray(mesh.vert_properties)[:, :3], np.asarray(mesh.tri_verts, dtype=np.int32))
