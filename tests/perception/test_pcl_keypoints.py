"""PCL keypoint saliency ("pcl_harris", "pcl_iss"): the peer program's contract (with stand-in programs, always
run) and PCL itself (known answers on cubes, ISS responses recomputed; skipped when the program is not built)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from perception.errors import SaliencyError
from perception.geometry import ObjectModel
from perception.saliency import (
    PCL_BINARY_ENV,
    PCL_METHODS,
    pcl_available,
    pcl_binary,
    pcl_keypoints,
    saliency,
)
from tactile.sampling import explore_object
from tactile.sensor import FSRSensor
from tests.perception.test_saliency import ROUND_MM, SIDE_MM, rounded_cube

needs_pcl = pytest.mark.skipif(
    not pcl_available(), reason=f"PCL peer {pcl_binary()} is not built (run `make peers`)"
)


def sharp_cube(side_mm: float = SIDE_MM, subdivisions: int = 5) -> ObjectModel:
    """A cube whose vertices lie on a regular grid of side / 2^subdivisions on every face."""
    box = o3d.geometry.TriangleMesh.create_box(side_mm, side_mm, side_mm).translate((-side_mm / 2,) * 3)
    box = box.subdivide_midpoint(subdivisions)
    return ObjectModel(np.asarray(box.vertices), np.asarray(box.triangles), name="sharp_cube")


@pytest.fixture(scope="module")
def cube() -> ObjectModel:
    return sharp_cube()


@pytest.fixture(scope="module")
def small_cube() -> ObjectModel:
    return rounded_cube(subdivisions=3)


def _program(folder: Path, body: str) -> Path:
    """An executable shell script standing in for the peer program (args: detector input output responses)."""
    path = folder / "fake_pcl"
    path.write_text("#!/bin/sh\n" + body + "\n")
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


# ------------------------------------------------------------------------- contract (stand-in programs)
def test_absent_program_names_make_peers(small_cube, tmp_path, monkeypatch):
    missing = tmp_path / "no_such_program"
    monkeypatch.setenv(PCL_BINARY_ENV, str(missing))
    assert not pcl_available()
    for method in PCL_METHODS:
        with pytest.raises(SaliencyError, match="make peers") as info:
            saliency(small_cube, method)
        assert str(missing) in str(info.value)
    with pytest.raises(SaliencyError, match="make peers"):
        explore_object(small_cube, "pcl_iss", 1)
    not_executable = tmp_path / "plain_file"
    not_executable.write_text("")
    monkeypatch.setenv(PCL_BINARY_ENV, str(not_executable))
    with pytest.raises(SaliencyError, match="make peers"):
        saliency(small_cube, "pcl_harris")


def test_program_gets_vertices_and_normals_and_its_ranking_is_kept(small_cube, tmp_path, monkeypatch):
    # Keypoints 5, 9, 2 with responses 0.1, 0.9, 0.5: strongest first is 9, 2, 5.
    copy = tmp_path / "input.xyz"
    monkeypatch.setenv(PCL_BINARY_ENV, str(_program(
        tmp_path, f"cp \"$2\" {copy}\nprintf '5\\n9\\n2\\n' > \"$3\"\nprintf '0.1\\n0.9\\n0.5\\n' > \"$4\"")))
    sal = saliency(small_cube, "pcl_harris")
    sent = np.loadtxt(copy)
    np.testing.assert_allclose(sent[:, :3], small_cube.vertices, rtol=1e-8, atol=1e-6)
    np.testing.assert_allclose(sent[:, 3:], small_cube.vertex_normals, rtol=1e-8, atol=1e-8)
    assert sal.keypoints.tolist() == [9, 2, 5]
    # Hand-computed tiers: rank r of K = 3 scores 1 - r / 6; every other vertex at most 0.5.
    np.testing.assert_allclose(sal.scores[[9, 2, 5]], [1.0, 5 / 6, 4 / 6])
    others = np.delete(sal.scores, [2, 5, 9])
    assert others.max() <= 0.5 and others.min() >= 0.0
    # Three keypoints and n <= 3: the keypoints themselves, by response.
    np.testing.assert_array_equal(sal.interest_points(3, min_distance_mm=0.0), small_cube.vertices[[9, 2, 5]])
    np.testing.assert_array_equal(sal.interest_points(1), small_cube.vertices[[9]])
    # n = 4 > 3 keypoints: all vertices are candidates; nothing outranks the keypoints.
    np.testing.assert_array_equal(sal.interest_points(4, min_distance_mm=0.0)[:3], small_cube.vertices[[9, 2, 5]])


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("kill -SEGV $$", "failed"),  # a native crash stays in the subprocess
        ("echo 'cannot read points' >&2; exit 1", "cannot read points"),
        ("printf '0\\n999999\\n' > \"$3\"; printf '1\\n2\\n' > \"$4\"", "does not match"),
        ("printf '0\\n1\\n' > \"$3\"; printf '1\\n' > \"$4\"", "does not match"),
        ("printf 'x\\n' > \"$3\"; printf '1\\n' > \"$4\"", "unreadable"),
    ],
)
def test_program_failures_become_saliency_errors(small_cube, tmp_path, monkeypatch, body, match):
    monkeypatch.setenv(PCL_BINARY_ENV, str(_program(tmp_path, body)))
    with pytest.raises(SaliencyError, match=match):
        pcl_keypoints(small_cube, "iss")


def test_program_past_its_time_limit_is_stopped(small_cube, tmp_path, monkeypatch):
    monkeypatch.setenv(PCL_BINARY_ENV, str(_program(tmp_path, "exec sleep 30")))
    with pytest.raises(SaliencyError, match="time limit"):
        pcl_keypoints(small_cube, "harris", timeout_s=0.5)


def test_no_keypoints_gives_zero_scores_and_still_n_points(small_cube, tmp_path, monkeypatch):
    monkeypatch.setenv(PCL_BINARY_ENV, str(_program(tmp_path, ": > \"$3\"; : > \"$4\"")))
    sal = saliency(small_cube, "pcl_iss")
    assert len(sal.keypoints) == 0 and not sal.scores.any()
    assert sal.interest_points(10).shape == (10, 3)


# ------------------------------------------------------------------------------- the real PCL program
@needs_pcl
def test_harris_keypoints_of_a_cube_are_its_corners(cube):
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * SIDE_MM / 2
    index, response = pcl_keypoints(cube, "harris")
    assert len(index) >= 8 and np.all(np.diff(response) <= 0)
    # The eight strongest keypoints: one at each corner (within 10 % of the side).
    d, nearest = cKDTree(corners).query(cube.vertices[index[:8]])
    assert d.max() <= 0.1 * SIDE_MM and sorted(nearest.tolist()) == list(range(8))
    # The interest points the guided strategies draw from are those corners too.
    points = saliency(cube, "pcl_harris").interest_points(8)
    assert cKDTree(corners).query(points)[0].max() <= 0.1 * SIDE_MM


@needs_pcl
def test_iss_responses_are_the_smallest_scatter_eigenvalue(small_cube):
    """Independent numpy recomputation: resolution = mean nearest-neighbour distance, salient radius 6 x it,
    response = smallest eigenvalue of sum (q - p)(q - p)^T over the neighbours q. (On the rounded cube: the
    sharp cube's lattice puts neighbours exactly on the radius, where float32 and float64 disagree.)"""
    model = small_cube
    index, response = pcl_keypoints(model, "iss")
    assert len(index) > 0
    tree = cKDTree(model.vertices)
    resolution = tree.query(model.vertices, k=2)[0][:, 1].mean()
    expected = []
    for i in index:
        near = model.vertices[tree.query_ball_point(model.vertices[i], 6 * resolution)] - model.vertices[i]
        expected.append(np.linalg.eigvalsh(near.T @ near)[0])
    np.testing.assert_allclose(response, expected, rtol=1e-3, atol=1e-6 * np.max(expected))


@needs_pcl
@pytest.mark.parametrize("method", PCL_METHODS)
def test_keypoints_are_on_the_surface_and_repeatable(small_cube, method):
    first, second = saliency(small_cube, method), saliency(small_cube, method)
    assert first.keypoints.tobytes() == second.keypoints.tobytes()
    assert first.scores.tobytes() == second.scores.tobytes()
    points = first.interest_points(10)
    assert first.interest_points(10).tobytes() == points.tobytes()
    _, distance = small_cube.closest_points(points)
    assert distance.max() <= 1e-4 * small_cube.diagonal


@needs_pcl
def test_iss_keypoints_of_a_rounded_cube_are_its_corners_and_edges():
    """ISS ranks by the smallest scatter eigenvalue: largest where the surface bends in every direction (the
    sphere-octant corners), zero on the flat faces. The 8 strongest are one per corner; none is on a face."""
    model = rounded_cube(subdivisions=5)  # vertex spacing about 2 mm, salient radius above the 8 mm rounding
    rounded = (np.abs(model.vertices) > SIDE_MM / 2 - ROUND_MM + 1e-6).sum(axis=1)  # coordinates in the band
    index, _ = pcl_keypoints(model, "iss")
    assert len(index) >= 8
    assert np.all(rounded[index] >= 2)  # on edges or corners, never on a flat face
    assert np.all(rounded[index[:8]] == 3)
    octants = {tuple(v) for v in np.sign(model.vertices[index[:8]]).astype(int)}
    assert len(octants) == 8


@needs_pcl
def test_explore_with_pcl_iss_gives_finite_sequences(small_cube):
    sequences = explore_object(small_cube, "pcl_iss", 2, sensor=FSRSensor(rows=8, cols=8), probes=5, seed=3)
    assert len(sequences) == 2 and all(s.strategy == "pcl_iss" for s in sequences)
    for s in sequences:
        assert np.isfinite(s.frames).all() and np.isfinite(s.positions).all() and np.isfinite(s.normals).all()
    again = explore_object(small_cube, "pcl_iss", 2, sensor=FSRSensor(rows=8, cols=8), probes=5, seed=3)
    for a, b in zip(sequences, again, strict=True):
        np.testing.assert_array_equal(a.frames, b.frames)


def test_pcl_available_follows_the_environment(tmp_path, monkeypatch):
    program = _program(tmp_path, "exit 0")
    monkeypatch.setenv(PCL_BINARY_ENV, str(program))
    assert pcl_available()
    os.chmod(program, 0o600)
    assert not pcl_available()
