"""The camera pipeline as a library call (fusion.camera): sources it accepts and refuses before any capture."""

from __future__ import annotations

import pytest

from fusion.camera import acquire
from perception.errors import DatasetError, InvalidArgumentError


class TestAcquire:
    def test_refuses_bad_sources_at_once(self, tmp_path):
        with pytest.raises(InvalidArgumentError, match="views"):
            acquire("virtual:mug", views=0)
        with pytest.raises(DatasetError, match="virtual:<class>/<seed>"):
            acquire("virtual:mug/first")
        with pytest.raises(DatasetError, match="recording folder"):
            acquire(str(tmp_path / "nowhere"))

    def test_a_virtual_capture_knows_its_truth(self):
        frames, truth, _, true_class = acquire("virtual:box/1", views=1, distance_mm=450.0)
        assert len(frames) == 1 and true_class == "box" and truth.name.startswith("box")
        assert frames[0].depth_mm.shape == frames[0].color.shape[:2]
