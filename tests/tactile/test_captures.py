"""Capture-like training objects: a virtual capture is the camera pipeline's reconstruction (the same bytes as
capturing and reconstructing by hand), at the training size in the pose-free frame, close to the true surface;
training specs name CAD meshes and captures as documented, and a store generated from them holds the capture."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from perception.camera import VirtualOakCamera
from perception.errors import DatasetError, InvalidArgumentError, InvalidMeshError
from perception.geometry import ObjectModel, random_rotation, rescale, rotate, surface_centroid
from perception.reconstruct.multiview import reconstruct_frames
from perception.reconstruct.surface import surface_error
from perception.shapes import make_object
from tactile.captures import (
    SOURCES,
    capture_name,
    catalogue_capture,
    is_capture,
    resting_rotation,
    training_specs,
    virtual_capture,
)
from tactile.dataset import generate, open_dataset
from tactile.sensor import FSRSensor


@pytest.fixture(scope="module")
def can_capture():
    """Catalogue can 3, four virtual OAK views at 0.5 m, camera seed 3."""
    return virtual_capture(make_object("can", 3), views=4, distance_mm=500.0, seed=3)


class TestVirtualCapture:
    def test_is_the_camera_pipeline_rescaled(self, can_capture):
        """Same bytes as VirtualOakCamera -> reconstruct_frames -> rescale done by hand with the same seed."""
        camera = VirtualOakCamera(make_object("can", 3), seed=3)
        rec = reconstruct_frames(camera.capture_views(4, 500.0), target=camera.target, seed=3)
        expected = rescale(rec.model, 150.0)
        assert np.array_equal(can_capture.model.vertices, expected.vertices)
        assert np.array_equal(can_capture.model.triangles, expected.triangles)
        assert np.array_equal(can_capture.world.vertices, rec.model.vertices)
        assert np.array_equal(can_capture.truth.vertices, camera.truth.vertices)

    def test_is_at_the_training_size_in_the_pose_free_frame(self, can_capture):
        """Centred on its surface centroid, enclosing sphere about it 150 mm across (to 1e-6 of the size)."""
        model = can_capture.model
        centre = surface_centroid(model.vertices, model.triangles)
        assert np.linalg.norm(centre) < 150e-6
        assert np.linalg.norm(model.vertices - centre, axis=1).max() == pytest.approx(75.0, abs=150e-6)

    def test_names_and_labels_like_the_object(self, can_capture):
        assert can_capture.model.name == "can/3@capture" and can_capture.model.label == "can"
        assert can_capture.seconds > 0

    def test_lies_on_the_true_surface(self, can_capture):
        """A can is what a stereo camera sees well: the closed reconstruction lies within a millimetre of the
        true surface in the world, and within 1.5 mm of the CAD mesh at the training size (both frames)."""
        assert surface_error(can_capture.world, can_capture.truth)["mean_mm"] < 1.0
        error = surface_error(can_capture.model, make_object("can", 3))
        assert error["mean_mm"] < 1.5 and error["coverage_mean_mm"] < 1.5

    @pytest.mark.parametrize("kwargs", [{"views": 0}, {"views": 2.5}, {"views": True}, {"distance_mm": 0.0},
                                        {"distance_mm": float("nan")}, {"size_mm": -1.0}, {"size_mm": "150"}])
    def test_refuses_bad_settings(self, kwargs):
        with pytest.raises(InvalidArgumentError):
            virtual_capture(make_object("box", 0), **kwargs)
        with pytest.raises(InvalidArgumentError):
            catalogue_capture("box", 0, **kwargs)

    def test_looks_from_the_elevation_asked(self):
        """elevation_deg and the reconstruction settings reach the camera and reconstruct_frames: the same bytes
        as one view at 70 degrees reconstructed by hand with the real-camera settings."""
        settings = {"method": "convex", "voxel_mm": 3.0, "drop_flying": True}
        cap = virtual_capture(make_object("box", 1), views=1, distance_mm=550.0, seed=4, elevation_deg=70.0,
                              reconstruct=settings)
        camera = VirtualOakCamera(make_object("box", 1), seed=4)
        (frame,) = camera.capture_views(1, 550.0, 70.0)
        up = frame.pose[:3, 2] @ np.array([0.0, 0.0, -1.0])  # the optical axis points down at 70 degrees
        assert np.degrees(np.arcsin(up)) == pytest.approx(70.0)
        rec = reconstruct_frames([frame], target=camera.target, seed=4, **settings)
        assert np.array_equal(cap.world.vertices, rec.model.vertices)
        assert np.array_equal(cap.model.vertices, rescale(rec.model, 150.0).vertices)

    @pytest.mark.parametrize("kwargs", [{"elevation_deg": 0.0}, {"elevation_deg": 90.0}, {"elevation_deg": True},
                                        {"elevation_deg": float("nan")}, {"reconstruct": {"icp": False}}])
    def test_refuses_a_bad_elevation_or_setting(self, kwargs):
        with pytest.raises(InvalidArgumentError, match=next(iter(kwargs)).split("_")[0]):
            virtual_capture(make_object("box", 0), **kwargs)

    @pytest.mark.parametrize("turn", [float("inf"), float("nan"), "90", True])
    def test_refuses_a_bad_turn(self, turn):
        with pytest.raises(InvalidArgumentError, match="turn_deg"):
            catalogue_capture("box", 0, turn_deg=turn)


def _cuboid(a: float, b: float, c: float) -> ObjectModel:
    """An a x b x c mm box centred at the origin (12 triangles, outward)."""
    v = np.array([[x, y, z] for x in (-a / 2, a / 2) for y in (-b / 2, b / 2) for z in (-c / 2, c / 2)])
    t = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                  [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return ObjectModel(v, t, name="cuboid")


class TestRestingRotation:
    def test_a_box_lies_on_a_face(self):
        """Dropped in any orientation, a 40 x 80 x 160 mm box comes to rest on one of its faces (four corners on
        the table): its height is one of its three sides, never a corner's tilt."""
        box = _cuboid(40.0, 80.0, 160.0)
        heights = []
        for seed in range(60):
            v = rotate(box, resting_rotation(box, seed)).vertices
            low = v[:, 2] - v[:, 2].min()
            assert (low < 1e-6).sum() == 4
            heights.append(round(float(np.ptp(v[:, 2])), 6))
        counts = {h: heights.count(h) for h in set(heights)}
        assert set(counts) <= {40.0, 80.0, 160.0}
        # The drop's odds: the broad face's basin is the widest, standing on end the narrowest.
        assert counts.get(40.0, 0) > counts.get(80.0, 0) > counts.get(160.0, 0)

    def test_rests_stably_and_repeats(self):
        """On every resting face the centre of mass lies above the support (inside its convex hull); the same seed
        gives the same bytes; the result is a proper rotation."""
        from scipy.spatial import Delaunay

        model = rotate(make_object("mug", 1), random_rotation(5))
        for seed in range(10):
            r = resting_rotation(model, seed)
            assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
            assert np.array_equal(r, resting_rotation(model, seed))
            turned = rotate(model, r)
            v = turned.vertices
            support = v[v[:, 2] - v[:, 2].min() < 1e-6 * model.size][:, :2]
            assert len(support) >= 3
            assert Delaunay(support).find_simplex(turned.center[:2]) >= 0

    def test_refuses_a_flat_mesh(self):
        flat = ObjectModel(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]), np.array([[0, 1, 2], [1, 3, 2]]))
        with pytest.raises(InvalidMeshError, match="no resting pose"):
            resting_rotation(flat, 0)


class TestTrainingSpecs:
    PAIRS = (("mug", 0), ("box", 2))

    def test_sources_name_cad_meshes_and_captures(self):
        """CAD objects are named as generate names catalogue pairs, captures "<class>/<seed>@capture", CAD first."""
        names = {s: [(spec.name, spec.label) for spec in training_specs(self.PAIRS, s)] for s in SOURCES}
        assert names["cad"] == [("mug/0", "mug"), ("box/2", "box")]
        assert names["capture"] == [("mug/0@capture", "mug"), ("box/2@capture", "box")]
        assert names["both"] == names["cad"] + names["capture"]
        cad = training_specs(self.PAIRS, "cad")
        assert [s.catalogue for s in cad] == [("mug", 0), ("box", 2)]

    def test_capture_specs_load_catalogue_captures_in_a_worker(self):
        """The loader is a picklable partial of catalogue_capture with the capture settings."""
        spec = training_specs([("can", 3)], "capture", views=3, distance_mm=450.0, size_mm=120.0)[0]
        loader = pickle.loads(pickle.dumps(spec.loader))
        assert loader.func is catalogue_capture and loader.args == ("can", 3)
        assert loader.keywords == {"views": 3, "distance_mm": 450.0, "size_mm": 120.0}

    def test_several_captures_look_from_between_the_views(self):
        """Capture k of n turns the object by k * 360 / (views * n) degrees and steps the camera seed."""
        specs = training_specs([("mug", 2)], "capture", views=4, captures_per_object=3)
        assert [s.name for s in specs] == ["mug/2@capture", "mug/2@capture1", "mug/2@capture2"]
        assert specs[0].loader.keywords == {"views": 4, "distance_mm": 500.0, "size_mm": 150.0}
        for k, spec in enumerate(specs[1:], start=1):
            assert spec.loader.keywords["turn_deg"] == pytest.approx(30.0 * k)
            assert spec.loader.keywords["camera_seed"] == 2 + 100_003 * k
        with pytest.raises(InvalidArgumentError, match="captures_per_object"):
            training_specs([("mug", 2)], "capture", captures_per_object=0)

    def test_names_tell_captures_apart(self):
        assert capture_name("mug/0") == "mug/0@capture" and capture_name("mug/0", 2) == "mug/0@capture2"
        assert is_capture("mug/0@capture") and is_capture("mug/0@capture12")
        assert not is_capture("mug/0") and not is_capture("mug/0@captured") and not is_capture("a@capture/b")

    @pytest.mark.parametrize("objects, message", [
        ([("mug", 0)], None),
        ([("mug", True)], r"\('mug', True\): the seed must be a non-negative integer, got True"),
        ([("mug", 0.5)], r"\('mug', 0.5\): the seed must be a non-negative integer, got 0.5"),
        (["mug"], r"object 'mug': expected \(path, label\)"),
        ([("teapot", 0)], "unknown class 'teapot'"),
        ([("mug", -1)], "the seed must be >= 0"),
        ([("mug", 0), ("mug", 0)], "both named 'mug/0'"),
    ])
    def test_checks_the_objects_as_generate_does(self, objects, message):
        if message is None:
            assert len(training_specs(objects, "both")) == 2
        else:
            with pytest.raises(DatasetError, match=message):
                training_specs(objects, "both")

    def test_refuses_an_unknown_source(self):
        with pytest.raises(InvalidArgumentError, match="cad, capture, both"):
            training_specs(self.PAIRS, "scan")

    def test_a_store_holds_the_capture(self, can_capture, tmp_path):
        """generate reconstructs the capture in its worker: every stored probe lies on the capture's surface."""
        out = tmp_path / "captures.zarr"
        report = generate(training_specs([("can", 3)], "capture"), out, strategies=("blind",), contours_per_object=2,
                          sensor=FSRSensor(rows=8, cols=8), probes=10, workers=1, progress=False)
        assert not report.failed
        data = open_dataset(out)
        assert data.object_names == ("can/3@capture",) and data.class_names == ("can",)
        positions = data.load().positions.reshape(-1, 3)
        _, distance = can_capture.model.closest_points(positions)
        assert distance.max() < 1e-3


@pytest.fixture(scope="module")
def box_file(tmp_path_factory):
    """A 40 x 60 x 100 mm box as an OFF file (trimesh's box, written here)."""
    import trimesh

    path = tmp_path_factory.mktemp("meshes") / "crate.off"
    trimesh.creation.box((40.0, 60.0, 100.0)).export(path)
    return path


class TestCapturesOfAnyObject:
    """Captures of objects that are not built in (mesh files), marked as made from their object."""

    def test_file_objects_get_object_capture_loaders_made_from_them(self, box_file):
        from tactile.captures import object_capture

        cad, first, second = training_specs([(box_file, "crate")], "both", captures_per_object=2)
        assert (cad.name, first.name, second.name) == ("crate/crate", "crate/crate@capture", "crate/crate@capture1")
        for capture in (first, second):
            assert capture.made_from is cad and capture.label == "crate"
            loader = pickle.loads(pickle.dumps(capture.loader))
            assert loader.func is object_capture and loader.args == (cad,)
        assert "camera_seed" not in first.loader.keywords and second.loader.keywords["turn_deg"] == pytest.approx(45.0)
        assert first.to_dict()["made_from"] == cad.to_dict()
        with pytest.raises(InvalidArgumentError, match="made from another object already"):
            training_specs([first], "both")

    def test_a_posed_catalogue_object_is_captured_resting(self):
        """A catalogue spec in a random pose is no longer upright: it is set down like a file."""
        from tactile.captures import object_capture
        from tactile.dataset.objects import ObjectSpec

        posed = ObjectSpec("mug/1", "mug", catalogue=("mug", 1), rotation_seed=5)
        (capture,) = training_specs([posed], "capture")
        assert capture.loader.func is object_capture and capture.made_from is posed

    def test_a_file_capture_is_the_box_at_the_training_size(self, box_file):
        """The capture of the box, set down on a face and seen from 4 views, comes back the box scaled so that its
        half-diagonal is 75 mm (the 150 mm enclosing sphere about its centre): oriented-bounding-box extents
        (trimesh's) and volume within 3 % of that box's."""
        import trimesh

        from tactile.captures import object_capture
        from tactile.dataset.objects import object_specs

        (spec,) = object_specs([(box_file, "crate")])
        model = object_capture(spec)
        assert model.is_watertight and model.name == "crate/crate@capture" and model.label == "crate"
        mesh = trimesh.Trimesh(model.vertices, model.triangles, process=False)
        scale = 75.0 / np.linalg.norm([20.0, 30.0, 50.0])
        extents = np.sort(mesh.bounding_box_oriented.primitive.extents)
        assert extents == pytest.approx(scale * np.array([40.0, 60.0, 100.0]), rel=0.03)
        assert mesh.volume == pytest.approx(40.0 * 60.0 * 100.0 * scale**3, rel=0.03)


class TestSplitsKeepCapturesWithTheirObjects:
    """A store of objects and things made from them (stand-ins for captures: another catalogue instance, loaded
    cheaply) is split by what each was made from: an object and its captures are always on one side."""

    @pytest.fixture(scope="class")
    @classmethod
    def store(cls, tmp_path_factory):
        import functools

        from tactile.dataset.objects import ObjectSpec, object_specs

        cad = object_specs([(c, s) for c in ("box", "can") for s in range(3)])
        made = [ObjectSpec(capture_name(spec.name, k), spec.label, made_from=spec,
                           loader=functools.partial(make_object, spec.label, 10 + 2 * i + k))
                for i, spec in enumerate(cad) for k in range(2)]
        out = tmp_path_factory.mktemp("made") / "store.zarr"
        report = generate(cad + made, out, strategies=("blind",), contours_per_object=2,
                          sensor=FSRSensor(rows=4, cols=4), probes=4, workers=1, progress=False)
        assert not report.failed
        return open_dataset(out)

    def test_a_capture_is_made_of_its_object(self, store):
        meshes = dict(zip(store.object_names, store.mesh_ids().tolist()))
        assert meshes["can/2@capture1"] == meshes["can/2@capture"] == meshes["can/2"] == "catalogue:can/2"
        assert len(set(meshes.values())) == 6

    def test_every_split_and_fold_keeps_the_groups_whole(self, store):
        base = np.array([name.split("@")[0] for name in store.object_names])[store.object_ids]
        for seed in range(6):
            train, test = store.split_by_object(0.34, seed=seed)
            assert len(set(base[test])) == 2  # one of the three groups of each class
            splits = [(train, test), *store.kfold_by_object(3, seed=seed)]
            for tr, te in splits:
                assert not set(base[tr]) & set(base[te])
                assert sorted(np.concatenate([tr, te]).tolist()) == list(range(len(store)))
            assert all(len(set(base[te])) == 2 for _, te in splits[1:])  # three folds of two groups

    def test_without_made_from_the_folds_are_those_dealt_object_by_object(self, tmp_path):
        """Stores of objects made from different meshes split as before groups existed: each class's objects
        permuted by the seeded generator and dealt in turn (the rule written out here)."""
        out = tmp_path / "plain.zarr"
        generate([(c, s) for c in ("box", "can", "ring") for s in range(4)], out, strategies=("blind",),
                 contours_per_object=1, sensor=FSRSensor(rows=4, cols=4), probes=4, workers=1, progress=False)
        ds = open_dataset(out)
        for seed in range(3):
            rng, turn, fold_of = np.random.default_rng(seed), 0, {}
            for c in range(3):
                for obj in rng.permutation(np.flatnonzero(ds.object_labels == c)):
                    fold_of[int(obj)], turn = turn % 3, turn + 1
            for f, (_, test) in enumerate(ds.kfold_by_object(3, seed=seed)):
                assert sorted({int(o) for o in ds.object_ids[test]}) == sorted(o for o, g in fold_of.items() if g == f)


def test_made_from_in_untrusted_settings(tmp_path):
    """What a store's settings say an object is made from is untrusted: a chain longer than MAX_MADE_FROM is refused,
    a FIFO or a device is not read (it would block or never end), a path with a NUL byte is only a name; a nested
    file is read by content, as a top-level one."""
    import hashlib
    import os

    from tactile.dataset.reader import MAX_MADE_FROM, _made_of

    mesh = tmp_path / "m.off"
    mesh.write_text("OFF\n")
    root = {"name": "m", "path": str(mesh)}
    chain = root
    for i in range(MAX_MADE_FROM):
        chain = {"name": f"c{i}", "made_from": chain}
    assert _made_of(chain, "s") == "sha256:" + hashlib.sha256(b"OFF\n").hexdigest()
    with pytest.raises(DatasetError, match=f"s: object 'x' is made from a chain of more than {MAX_MADE_FROM}"):
        _made_of({"name": "x", "made_from": chain}, "s")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for path in (str(fifo), "/dev/zero", "a\x00b"):
        assert _made_of({"name": "c", "made_from": {"name": "m", "path": path}}, "s") == "path:" + path
    assert _made_of({"name": "c", "made_from": ["not", "a", "dict"], "catalogue": ["mug", 1]}, "s") == \
        "catalogue:mug/1"


def test_files_are_told_apart_by_content_up_to_a_fixed_size(tmp_path, monkeypatch):
    """Copies of one file are one object up to MAX_HASHED_BYTES (a constant: the file_mb limit of the reader's
    environment does not change the groups); beyond it each path is its own; each file is read once per call."""
    import hashlib

    from tactile.dataset import reader

    small, copy, big = tmp_path / "a.off", tmp_path / "b.off", tmp_path / "c.off"
    small.write_bytes(b"x" * 10)
    copy.write_bytes(b"x" * 10)
    big.write_bytes(b"x" * 11)
    monkeypatch.setattr(reader, "MAX_HASHED_BYTES", 10)
    monkeypatch.setenv("VISUOTACTILE_MAX_FILE_MB", "0")
    digest = "sha256:" + hashlib.sha256(b"x" * 10).hexdigest()
    assert [reader._made_of({"name": n, "path": str(p)}, "s") for n, p in (("a", small), ("b", copy), ("c", big))] \
        == [digest, digest, f"path:{big}"]
    seen = {}
    reader._made_of({"name": "a", "path": str(small)}, "s", seen)
    small.write_bytes(b"y" * 10)  # not read again within one call
    assert reader._made_of({"name": "a@capture", "made_from": {"name": "a", "path": str(small)}}, "s", seen) == digest
