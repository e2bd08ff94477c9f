"""Stores are untrusted input: a FIFO, a deeply nested JSON file or an oversized file in one ends in one line and
exit 2 (or a damaged object in a verify report), never a hang, a traceback or an allocation sized by the file.
Commands that could hang or allocate run in a child process with a timeout (and a memory limit)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from fusion.cli import main
from tests._small_store import OBJECTS, small_knn_model

ROOT = Path(__file__).resolve().parents[2]
NESTED = "[" * 100_000 + "]" * 100_000


@pytest.fixture(scope="module")
def model(store, tmp_path_factory) -> Path:
    return small_knn_model(store, tmp_path_factory.mktemp("untrusted-model") / "knn.vtm")


def child(code: str, *, timeout: float = 60.0, extra_memory_mb: int | None = None) -> subprocess.CompletedProcess:
    """Run ``code`` in a child Python (after importing the toolkit); with ``extra_memory_mb`` its address space is
    limited to its size after the imports plus that much (an allocation sized by a file then shows as MemoryError)."""
    script = textwrap.dedent("""
        import resource, sys
        import numpy, zarr, torch, sklearn.svm, sklearn.neighbors  # noqa: F401 -- before the limit
        import fusion.cli, fusion.training, fusion.evaluate, fusion.conventional, tactile.dataset.integrity  # noqa
        from perception.errors import DatasetError
        from tactile.dataset import generate
        from tactile.sensor import FSRSensor
        extra = {extra!r}
        if extra is not None:
            with open("/proc/self/status") as f:
                vm = next(int(line.split()[1]) for line in f if line.startswith("VmSize:")) * 1024
            resource.setrlimit(resource.RLIMIT_AS, (vm + extra * 2**20, vm + extra * 2**20))
    """).format(extra=extra_memory_mb) + textwrap.dedent(code)
    try:
        return subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True,
                              timeout=timeout, env={**os.environ, "PYTHONPATH": str(ROOT)}, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail(f"hung for {timeout} s: {code.strip()}")


def cli(argv: list[str], **kwargs) -> subprocess.CompletedProcess:
    """``visuotactile ARGV`` in a child (see :func:`child`)."""
    return child(f"sys.exit(fusion.cli.main({argv!r}))", **kwargs)


def assert_clean(proc: subprocess.CompletedProcess, code: int, *names: str) -> None:
    """Exit ``code``, no traceback, no MemoryError; exit 2 is one line naming each of ``names``."""
    assert "Traceback" not in proc.stderr and "MemoryError" not in proc.stderr, proc.stderr[-1500:]
    assert proc.returncode == code, (proc.returncode, proc.stderr[-1500:])
    if code == 2:
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and all(name in lines[0] for name in names), lines


# ------------------------------------------------------------------------------------------- special files
@pytest.mark.parametrize("name", ["records/00000.json", "frames/zarr.json", "normals/zarr.json"])
def test_a_fifo_in_a_store_is_refused_not_waited_on(copy, model, name):
    """Opening a FIFO for reading blocks until a writer comes: verify, evaluate and a resumed generate hung in
    read_records or zarr's metadata read."""
    (copy / name).unlink()
    os.mkfifo(copy / name)
    assert_clean(cli(["verify", str(copy)], timeout=30), 2, name, "FIFO")
    assert_clean(cli(["evaluate", "--model", str(model), "--store", str(copy)], timeout=30), 2, name)
    resume = f"""
        try:
            generate({OBJECTS!r}, {str(copy)!r}, strategies="blind", contours_per_object=6,
                     sensor=FSRSensor(rows=8, cols=8), probes=6, seed=0, workers=1, progress=False)
        except DatasetError as exc:
            sys.exit(print(exc, file=sys.stderr) or 2)
    """
    assert_clean(child(resume, timeout=30), 2, name)


def test_a_symlink_out_of_the_store_is_refused(copy, tmp_path, capsys):
    """A store unpacked from an archive may link to any file of the machine (a device, another user's data)."""
    outside = tmp_path / "elsewhere.json"
    shutil.copy(copy / "normals" / "zarr.json", outside)
    (copy / "normals" / "zarr.json").unlink()
    (copy / "normals" / "zarr.json").symlink_to(outside)
    capsys.readouterr()
    assert main(["verify", str(copy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "normals/zarr.json" in err[0] and "outside the store" in err[0], err


# ------------------------------------------------------------------------------------------- nested JSON
def test_a_deeply_nested_record_is_damage_not_a_recursion_error(copy, model, capsys):
    """records/NNNNN.json of 100,000 nested lists: json raised RecursionError, which the record readers did not
    catch (a traceback from verify, evaluate, train and generate)."""
    (copy / "records" / "00000.json").write_text(NESTED)
    assert main(["verify", str(copy)]) == 1  # its object is damaged
    assert "box/0: its completion record is unreadable" in capsys.readouterr().out
    assert main(["evaluate", "--model", str(model), "--store", str(copy), "--no-progress"]) in (0, 2)
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("name", ["zarr.json", "normals/zarr.json"])
def test_deeply_nested_metadata_is_one_line_naming_the_file(copy, capsys, name):
    meta = json.loads((copy / name).read_text())
    (copy / name).write_text(json.dumps(meta)[:-1] + ', "x": ' + NESTED + "}")
    capsys.readouterr()
    assert main(["verify", str(copy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and name in err[0] and "nested" in err[0], err


# ------------------------------------------------------------------------------------------- sizes
def test_the_memory_limited_child_runs_a_clean_store(store, model):
    """The harness of the size tests: under the same limit a clean store verifies and evaluates."""
    assert_clean(cli(["verify", str(store)], extra_memory_mb=1024), 0)
    assert_clean(cli(["evaluate", "--model", str(model), "--store", str(store)], extra_memory_mb=1024), 0)


def test_an_oversized_record_is_damage_and_not_read(copy):
    """A 2 GiB (sparse) record was read whole (read_text): 4 GB of memory for a file that compresses to bytes."""
    with open(copy / "records" / "00000.json", "r+b") as f:
        f.truncate(2 << 30)
    proc = cli(["verify", str(copy)], extra_memory_mb=1024)
    assert_clean(proc, 1)
    assert "box/0: its completion record is unreadable" in proc.stdout


@pytest.mark.parametrize("name", ["zarr.json", "frames/zarr.json"])
def test_oversized_metadata_is_refused_before_it_is_read(copy, name):
    with open(copy / name, "r+b") as f:
        f.truncate(2 << 30)
    assert_clean(cli(["verify", str(copy)], extra_memory_mb=1024), 2, name, "bytes")


@pytest.mark.parametrize("array", ["normals", "frames"])
def test_an_oversized_chunk_file_is_damage_and_not_read(copy, model, array):
    """A chunk (or shard) file of 2 GiB (sparse) was read whole by zarr before its checksum failed: its size is
    checked against what its rows can take first (the object is damaged: verify reports it, evaluate refuses)."""
    chunk = copy / array / "c" / ("0/0/0/0" if array == "frames" else "0/0/0")
    with open(chunk, "r+b") as f:
        f.truncate(2 << 30)
    proc = cli(["verify", str(copy)], extra_memory_mb=1024)
    assert_clean(proc, 1)
    assert f"box/0: its {array} chunk {array}/c/0/0" in proc.stdout and "more than" in proc.stdout, proc.stdout
    proc = cli(["evaluate", "--model", str(model), "--store", str(copy)], extra_memory_mb=1024)
    assert_clean(proc, 2, "box/0", "is damaged", "bytes")


def test_a_damage_message_names_the_store_the_object_the_problem_and_the_repair():
    from tactile.dataset.store import damage_message

    assert damage_message(Path("runs/s.zarr"), "Cup/021", "its frames chunk frames/c/0/0/0 is missing") == (
        "runs/s.zarr: object 'Cup/021' is damaged: its frames chunk frames/c/0/0/0 is missing; "
        "`visuotactile verify runs/s.zarr` lists the damaged objects and re-running generate re-explores them")
