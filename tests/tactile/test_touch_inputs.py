"""Bad input to touch (and Toucher): counts above the documented limits of perception.limits are refused before
anything is cut or pressed, as the command line refuses them, and what is not an ObjectModel is named, with the
way to make one."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from perception.errors import InvalidArgumentError
from perception.shapes import make_object
from tactile.sensor import FSRSensor
from tactile.touching import Toucher, jitter_contour, touch

SMALL = FSRSensor(rows=4, cols=4)


@pytest.fixture(scope="module")
def box():
    return make_object("box", 0)


class TestCountLimits:
    def test_probes_above_the_default_limit_are_refused(self, box):
        """The limit is 10,000 probes per contour, the message the CLI gives for --probes."""
        with pytest.raises(InvalidArgumentError, match="box/0: probes: 10001 is above the limit of 10000 probes per "
                                                       r"contour \(set VISUOTACTILE_MAX_PROBES to raise it\)"):
            touch(box, "blind", 2, SMALL, probes=10_001)
        with pytest.raises(InvalidArgumentError, match="probes: 1000000 is above the limit"):
            touch(box, "blind", 2, SMALL, probes=10**6)

    def test_the_probe_limit_follows_its_variable(self, box, monkeypatch):
        monkeypatch.setenv("VISUOTACTILE_MAX_PROBES", "20")
        with pytest.raises(InvalidArgumentError, match="probes: 21 is above the limit of 20"):
            touch(box, "blind", 1, SMALL, probes=21)
        with pytest.raises(InvalidArgumentError, match="probes: 21 is above the limit of 20"):
            Toucher(box, "blind", probes=21)
        (sequence,) = touch(box, "blind", 1, SMALL, probes=20)  # at the limit: allowed
        assert sequence.frames.shape == (20, 4, 4)

    def test_contours_above_their_limit_are_refused(self, box, monkeypatch):
        monkeypatch.setenv("VISUOTACTILE_MAX_CONTOURS", "3")
        with pytest.raises(InvalidArgumentError, match="box/0: n_contours: 4 is above the limit of 3 contours per "
                                                       "object and strategy"):
            touch(box, "blind", 4, SMALL, probes=5)
        toucher = Toucher(box, "blind", probes=5)
        with pytest.raises(InvalidArgumentError, match="n_contours: 4 is above the limit of 3"):
            next(toucher.stream(4, seed=0))
        with pytest.raises(InvalidArgumentError, match="n_contours: 4 is above the limit of 3"):
            toucher.by_object(4, seed=0)
        assert len(touch(box, "blind", 3, SMALL, probes=5)) == 3

    def test_the_default_contour_limit_comes_first(self, box):
        """Checked before anything else about the contours (here: a plane list of the wrong length)."""
        with pytest.raises(InvalidArgumentError, match="n_contours: 100001 is above the limit of 100000"):
            touch(box, "blind", 100_001, SMALL, probes=2, planes=[])


class TestWhatIsTouched:
    @pytest.mark.parametrize("model", [o3d.geometry.TriangleMesh.create_box(), "box.off"],
                             ids=["open3d-mesh", "path"])
    def test_a_mesh_or_a_path_is_told_to_go_through_load_object(self, model):
        with pytest.raises(InvalidArgumentError, match="touch: expected a perception.ObjectModel, got .*"
                                                       r"load it with perception.load_object\(\.\.\.\) first"):
            touch(model, "blind", 2)
        with pytest.raises(InvalidArgumentError, match="Toucher: expected a perception.ObjectModel"):
            Toucher(model, "blind")

    def test_none_is_named(self):
        with pytest.raises(InvalidArgumentError, match="touch: expected a perception.ObjectModel, got NoneType$"):
            touch(None, "blind", 2)

    def test_a_sensor_that_is_not_an_fsr_sensor_is_named(self, box):
        with pytest.raises(InvalidArgumentError, match="box/0: sensor must be a tactile.FSRSensor, got dict"):
            touch(box, "blind", 2, {"rows": 4})

    @pytest.mark.parametrize("jitter", ["1", -1.0, float("nan"), True])
    def test_a_bad_jitter_is_named(self, box, jitter):
        with pytest.raises(InvalidArgumentError, match=r"pose jitter must be a finite number in \[0, 1000\] mm"):
            touch(box, "blind", 2, SMALL, probes=5, jitter_mm=jitter)

    def test_jitter_contour_takes_numpy_numbers(self, box):
        contours = []
        touch(box, "blind", 1, SMALL, probes=5, contours=contours)
        moved = jitter_contour(contours[0], np.float32(0.5), np.random.default_rng(0))
        assert moved.positions.shape == (5, 3) and not np.array_equal(moved.positions, contours[0].positions)
        assert jitter_contour(contours[0], np.int64(0), np.random.default_rng(0)) is contours[0]
