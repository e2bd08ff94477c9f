"""Every mesh of the shared real data sets loads, and its normals and curvature are finite.

Skipped, saying why, when ../shared/data is absent (set VISUOTACTILE_DATA to point elsewhere).
"""

from __future__ import annotations

import numpy as np
import pytest

from perception.geometry import list_collection, load_object


def check_finite(model) -> None:
    assert model.n_triangles > 0
    assert model.size == pytest.approx(150.0)
    assert np.isfinite(model.vertex_normals).all()
    np.testing.assert_allclose(np.linalg.norm(model.vertex_normals, axis=1), 1.0, atol=1e-9)
    c = model.curvature
    for array in (c.mean, c.gaussian, c.k1, c.k2, c.dir1, c.dir2):
        assert np.isfinite(array).all()


def test_all_shrec07_meshes_load(shrec07):
    items = list_collection(shrec07)
    assert len(items) == 100 and len({label for _, label in items}) == 10
    for path, label in items:
        model = load_object(path, label=label)
        check_finite(model)
        # The README promises watertight meshes; repair must not break that.
        assert model.is_watertight, path


def load_checked(folder, expected: int) -> list:
    """Load every OBJ in ``folder`` (there must be ``expected``), checking each is finite."""
    paths = sorted(folder.glob("*.obj"))
    assert len(paths) == expected
    models = [load_object(path) for path in paths]
    for model in models:
        check_finite(model)
    return models


def test_all_psb_open_polygon_soups_load(psb_open):
    for model in load_checked(psb_open, 20):
        assert not model.is_watertight, model.name  # these are the open ones


def test_all_ycb_meshes_load_with_texture_colours(ycb):
    """Every YCB mesh that comes with a material (.mtl + texture image) loads with its colours; the six
    without one (e.g. the cracker box) load plain."""
    for model in load_checked(ycb, 16):
        textured = (ycb / f"{model.name}.mtl").is_file()
        assert model.has_colors == textured, model.name
        if not textured:
            continue
        # Texture colours are real images, not a constant fill.
        assert model.vertex_colors.std(axis=0).max() > 0.02, model.name


@pytest.mark.slow
def test_attention_and_touch_on_every_open_and_scanned_mesh(psb_open, ycb):
    """Polygon soups and scans (non-manifold, several components, seams) survive the whole path, finite."""
    from perception.saliency import saliency
    from tactile import explore_object

    for model in [*load_checked(psb_open, 20), *load_checked(ycb, 16)]:
        for method in ("multiview", "mesh", "iss"):
            attention = saliency(model, method)
            assert np.isfinite(attention.scores).all() and np.isfinite(attention.interest_points(10)).all()
        for strategy in ("blind", "guided"):
            for seq in explore_object(model, strategy=strategy, n_contours=3, seed=1):
                for array in (seq.frames, seq.normals, seq.positions, seq.pad_sides_mm):
                    assert np.isfinite(array).all(), model.name
