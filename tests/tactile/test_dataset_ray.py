"""The Ray executor (extra ``dist``) on a local two-CPU Ray instance gives the local executor's store."""

from __future__ import annotations

import shutil
import tempfile

import pytest

from tactile.dataset import ObjectSpec, generate, open_dataset
from tests.tactile.test_dataset import BLIND, BLIND_OBJECTS, store_files

ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'visuotactile[dist]')")


@pytest.fixture(scope="module")
def local_ray():
    """One small Ray instance for the module (start-up takes seconds). Its session folder (logs, sockets) goes in a
    short temporary folder removed after, not in /tmp/ray where every run left one."""
    folder = tempfile.mkdtemp(prefix="vt-ray-")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False, _temp_dir=folder)
    yield
    ray.shutdown()
    shutil.rmtree(folder, ignore_errors=True)


def test_ray_store_equals_local_store(local_ray, tmp_path):
    objects = BLIND_OBJECTS[:2]
    generate(objects, tmp_path / "local", workers=1, **BLIND)
    report = generate(objects, tmp_path / "ray", executor="ray", **BLIND)
    assert report.completed == 2 and not report.failed
    assert store_files(tmp_path / "ray") == store_files(tmp_path / "local")
    assert ray.is_initialized()  # an instance the caller started is left running


def test_ray_records_a_failing_object_and_completes_the_rest(local_ray, tmp_path):
    missing = ObjectSpec("bad/missing", "bad", path=str(tmp_path / "missing.off"))
    report = generate([missing, ("mug", 0)], tmp_path / "s", executor="ray", **BLIND)
    assert report.completed == 1 and report.failed[0][0] == "bad/missing"
    assert "missing.off" in open_dataset(tmp_path / "s").failed["bad/missing"]
