"""A file fuzzer over ``load_object`` and ``load_points`` (:mod:`benchmarks.fuzz`).

Every case runs in a child process with a CPU-time and an address-space limit; a case passes when it ends
in a VisuotactileError or a finite, valid ObjectModel. A crash, a timeout, a MemoryError, any other
exception or an invalid model fails the test and is listed in the message.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks import fuzz
from perception.errors import VisuotactileError
from perception.geometry import load_object
from perception.meshio import read_mesh
from perception.reconstruct.pointfiles import read_points


def _report(results) -> str:
    lines = [fuzz.format_table(fuzz.summarize(results))]
    lines += [f"{r.case.family} {r.case.loader} {Path(r.case.path).name} ({r.case.note}): {r.outcome}: {r.detail}"
              for r in fuzz.failures(results)[:30]]
    return "\n".join(lines)


def _check(results, n_cases: int) -> None:
    assert len(results) == n_cases and all(r is not None for r in results)
    assert not fuzz.failures(results), _report(results)
    assert {r.case.family for r in results} == set(fuzz.FAMILIES)
    # Every unmodified seed loads, a hand-written mesh to the vertex and triangle counts it was written with.
    for r in results:
        if r.case.family == "seed":
            assert r.outcome == "loaded", f"{r.case.note}: {r.detail}"
            assert r.case.expect is None or r.shape == tuple(r.case.expect), r.case.note
    # A header that claims more elements than the file holds is refused, never trusted (except the PTS
    # count and the PCD WIDTH, which the readers do not use: POINTS and the lines count).
    for r in results:
        if r.case.family == "huge_count" and r.outcome == "loaded":
            assert r.case.path.endswith(".pts") or "WIDTH" in r.case.note, r.case.note


def test_harness_reports_crashes_timeouts_and_memory_as_failures(tmp_path):
    kinds = ["_refuse", "_abort", "_refuse", "_hang", "_refuse", "_alloc", "_segfault", "_refuse"]
    cases = [fuzz.Case("selftest", k, str(tmp_path / f"case{i}"), k) for i, k in enumerate(kinds)]
    results = fuzz.run_cases(cases, timeout_s=2.0, memory_mb=1024)
    assert [r.outcome for r in results] == [
        "refused", "crash", "refused", "timeout", "refused", "memory", "crash", "refused",
    ]
    assert "SIGABRT" in results[1].detail and "SIGSEGV" in results[6].detail
    assert [r.case.loader for r in fuzz.failures(results)] == ["_abort", "_hang", "_alloc", "_segfault"]


def test_fuzz_fast(tmp_path):
    cases = fuzz.make_cases(tmp_path, per_family=3)
    results = fuzz.run_cases(cases)
    _check(results, len(cases))
    print("\n" + _report(results))


@pytest.mark.slow
def test_fuzz_slow(tmp_path):
    cases = fuzz.make_cases(tmp_path, per_family=125, seed=1)
    assert len(cases) >= 1000
    results = fuzz.run_cases(cases)
    _check(results, len(cases))
    print("\n" + _report(results))


def test_cases_are_deterministic(tmp_path):
    a = fuzz.make_cases(tmp_path / "a", per_family=2, real=False)
    b = fuzz.make_cases(tmp_path / "b", per_family=2, real=False)
    assert [Path(c.path).read_bytes() for c in a] == [Path(c.path).read_bytes() for c in b]


@pytest.mark.parametrize("name", ["cloud-ascii.pcd", "cloud-binary.pcd", "cloud-ascii.ply", "cloud-le.ply"])
def test_truncated_point_files_are_refused_or_hold_only_true_points(tmp_path, name):
    # Open3D's readers returned the declared number of points, the unread ones zero or uninitialised.
    seed = next(s for s in fuzz.point_seeds() if s.name == name)
    truth, _ = fuzz._cloud()
    _refused_or_subset(tmp_path / name, seed, lambda p: read_points(p)[0], truth)


@pytest.mark.parametrize("name", ["ico-ascii.ply", "ico-le.ply", "ico-be.ply", "cube-mixed-le.ply"])
def test_truncated_ply_meshes_are_refused_or_hold_only_true_vertices(tmp_path, name):
    # The same for meshes; and Open3D's PLY reader segfaulted on damaged face lists (the fuzzer's crashes).
    seed = next(s for s in fuzz.mesh_seeds() if s.name == name)
    truth = fuzz._icosahedron()[0] if name.startswith("ico") else np.array(
        [[x, y, z] for x in (0, 10) for y in (0, 10) for z in (0, 10)], dtype=float)
    _refused_or_subset(tmp_path / name, seed, lambda p: read_mesh(p).vertices, truth)


def _refused_or_subset(path: Path, seed, read, truth: np.ndarray) -> None:
    """Cut ``seed`` at 60 lengths through its payload: each read is refused or holds only ``truth`` rows."""
    path.write_bytes(seed.data)
    assert np.abs(read(path) - truth).max() < 1e-4  # the whole file reads back exactly
    loaded = 0
    for cut in np.linspace(seed.body, len(seed.data) - 1, 60).astype(int):
        path.write_bytes(seed.data[:cut])
        try:
            rows = read(path)
        except VisuotactileError:
            continue
        loaded += 1
        nearest = np.abs(rows[:, None, :] - truth[None]).max(axis=2).min(axis=1)
        assert nearest.max() < 1e-4, f"cut at {cut}: {int((nearest >= 1e-4).sum())} invented rows"
    assert loaded <= 1  # at most the cut that drops only the last newline


def test_face_normals_of_a_needle_are_unit_found_by_the_fuzzer(tmp_path):
    # A cube with one corner moved to x = 1e308 loads (scaled to 100 mm) as a needle 1e306 times longer than
    # wide: the squares in |cross| underflowed to zero and faces with a non-zero cross product got zero normals.
    corners = [[1e308, 0, 0]] + [[x, y, z] for x in (0, 10) for y in (0, 10) for z in (0, 10)][1:]
    quads = ["4 0 1 3 2", "4 4 6 7 5", "4 0 4 5 1", "4 2 3 7 6", "4 0 2 6 4", "4 1 5 7 3"]
    path = tmp_path / "needle.off"
    path.write_text("OFF\n8 6 0\n" + "".join(f"{x!r} {y} {z}\n" for x, y, z in corners) + "\n".join(quads) + "\n")
    model = load_object(path)
    v, t = model.vertices, model.triangles
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    live = (cross != 0).any(axis=1)
    assert live.any() and np.abs(cross[live]).max() < 1e-150  # the needle's tiny faces are there
    normals = model.triangle_normals
    np.testing.assert_allclose(np.linalg.norm(normals[live], axis=1), 1.0, rtol=1e-12)
    assert (np.sign(normals[live]) == np.sign(cross[live])).all()
    assert (normals[~live] == 0).all()


# ------------------------------------------------------------------------- stores, model files, recordings
def _files_report(results) -> str:
    from benchmarks import fuzz_files

    return "\n".join([fuzz_files.format_table(fuzz_files.summarize(results))] + [
        f"{r.case.family} ({r.case.note}): {r.outcome}: {r.detail}" for r in fuzz_files.failures(results)[:30]])


def test_file_fuzz_fast(tmp_path):
    # A sample of the stores / model files / recordings fuzzer (benchmarks.fuzz_files runs 1,000 cases).
    from benchmarks import fuzz_files

    results, clean = fuzz_files.fuzz(21, seed=3, folder=tmp_path)
    assert len(results) == 21 and {r.case.family for r in results} == set(fuzz_files.FAMILIES)
    assert clean["decisions"] == 8  # 2 objects x 4 contours, one touch each
    assert not fuzz_files.failures(results), _files_report(results)
    assert all(r.outcome == "refused" for r in results if r.case.damaged or r.case.marker)
    assert all(np.isfinite(r.peak_mb) and r.peak_mb > 0 for r in results)
    print("\n" + _files_report(results))


def test_file_fuzz_classifies_what_it_must_count_as_failures():
    from benchmarks.fuzz_files import Case, Result, classify, judge

    def record(code=0, stderr=(), escaped=None, payload=False):
        return {"code": code, "stderr": list(stderr), "escaped": escaped, "payload": payload}

    store = Case("store_chunk", ["evaluate"], "", damaged=True, compare=True)
    plain = Case("store_meta", ["evaluate"], "", compare=True)
    assert classify(store, record(0))[0] == "wrong"  # a damaged store that evaluates
    assert classify(store, record(2, ["visuotactile evaluate: error: damaged"]))[0] == "refused"
    assert classify(plain, record(2, ["a", "b"]))[0] == "foreign"  # not one line
    assert classify(plain, record(1, ["Traceback"]))[0] == "foreign"
    assert classify(plain, record(None, escaped=("foreign", "KeyError: 'x'")))[0] == "foreign"
    assert classify(plain, record(2, ["refused"], payload=True))[0] == "payload"
    clean = {"decisions": 8, "accuracy": {"value": 0.5}}
    results = [Result(plain, "ok", "", 0.1, 1.0, dict(clean)), Result(plain, "ok", "", 0.1, 1.0,
                                                                      {"decisions": 8, "accuracy": {"value": 0.9}})]
    judge(results, clean)
    assert [r.outcome for r in results] == ["ok", "wrong"]  # other numbers from an edited store: silent and wrong
