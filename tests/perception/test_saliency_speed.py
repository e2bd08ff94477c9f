"""The fast multiview paths equal their plain definitions: the stacked render equals one view at a time, and each
rewritten channel equals the straightforward formula it replaces (same bytes where the arithmetic is the same)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy import ndimage, signal

from perception import channels, primitives
from perception.geometry import ObjectModel
from perception.render import _stacked_rays, make_camera, render_stack, render_views, view_directions


def _box() -> ObjectModel:
    box = o3d.geometry.TriangleMesh.create_box(60.0, 40.0, 30.0).translate((-30.0, -20.0, -15.0))
    box = box.subdivide_midpoint(3)
    return ObjectModel(np.asarray(box.vertices), np.asarray(box.triangles), name="box")


@pytest.mark.parametrize("model", [primitives.sphere(40.0, 3), _box()], ids=["sphere", "box"])
def test_stacked_render_equals_one_view_at_a_time(model):
    directions = np.vstack([view_directions(7), [[0.0, 0.0, 1.0]]])
    stack = render_stack(model, width=48, height=40, directions=directions)
    assert stack.mask.shape == (8, 40, 48) and len(stack) == 8
    assert stack.mask.any(axis=(1, 2)).all()
    for k, d in enumerate(directions):
        (alone,) = render_views(model, width=48, height=40, directions=d[None])
        for name in ("depth", "mask", "normal", "intensity", "triangle_ids", "barycentric"):
            got, want = getattr(stack, name)[k], getattr(alone, name)
            assert got.dtype == want.dtype and got.shape == want.shape
            np.testing.assert_allclose(got, want, atol=1e-6, rtol=0)
            assert got.tobytes() == want.tobytes(), name
        # Background conventions: ids -1 and zeros; barycentric coordinates sum to 1 on hits.
        assert (stack.triangle_ids[k][~stack.mask[k]] == -1).all()
        assert not stack.normal[k][~stack.mask[k]].any()
        np.testing.assert_allclose(stack.barycentric[k][stack.mask[k]].sum(axis=1), 1.0, atol=1e-6)
    # The views are slices of the stack, not copies.
    view = stack.views[3]
    assert np.shares_memory(view.depth, stack.depth) and view.camera is stack.cameras[3]


def test_stacked_rays_equal_each_cameras_rays():
    model = _box()
    cameras = [make_camera(model, d, 20, 12, model.principal_frame) for d in view_directions(5)]
    rays = _stacked_rays(model, cameras)
    assert rays.dtype == np.float32 and rays.shape == (5 * 20 * 12, 6)
    assert rays.tobytes() == np.concatenate([c.rays(model) for c in cameras]).tobytes()


@pytest.fixture(scope="module")
def images():
    """Four 32 x 40 views: smooth shading with texture on a blob mask that touches the image edges (so the
    symmetry votes wrap round), plus one empty view."""
    rng = np.random.default_rng(7)
    rows, cols = np.mgrid[0:32, 0:40]
    mask = np.stack(
        [((rows - cy) / ry) ** 2 + ((cols - cx) / rx) ** 2 < 1 for cy, cx, ry, rx in
         [(16, 20, 12, 15), (3, 20, 10, 25), (16, 38, 14, 9), (0, 0, 0.1, 0.1)]]
    )
    intensity = np.clip(0.5 + 0.3 * np.sin(rows / 3.0 + cols / 5.0) + 0.1 * rng.random((4, 32, 40)), 0, 1) * mask
    return intensity, mask


def _plain_symmetry(filled, mask):
    gx, gy = ndimage.sobel(filled, axis=2), ndimage.sobel(filled, axis=1)
    strength, phase = np.log1p(np.hypot(gx, gy)), np.arctan2(gy, gx)
    total = np.zeros(filled.shape)
    for radius in (2, 4, 6):
        for alpha in np.arange(8) * np.pi / 8:
            dy, dx = round(radius * np.sin(alpha)), round(radius * np.cos(alpha))
            a = np.arctan2(dy, dx)
            t1, t2 = np.roll(phase, (dy, dx), axis=(1, 2)), np.roll(phase, (-dy, -dx), axis=(1, 2))
            r1, r2 = np.roll(strength, (dy, dx), axis=(1, 2)), np.roll(strength, (-dy, -dx), axis=(1, 2))
            weight = (1 - np.cos(t1 + t2 - 2 * a)) * (1 - np.cos(t1 - t2)) / 4
            total += np.exp(-2 * np.hypot(dy, dx) / 8) * weight * r1 * r2
    return total * mask


def _plain_orientation(filled, mask):
    total = np.zeros(filled.shape)
    for theta in np.deg2rad([0.0, 45.0, 90.0, 135.0]):
        response = np.abs(signal.fftconvolve(filled, channels._gabor_kernel(theta)[None], mode="same", axes=(1, 2)))
        total += channels.itti_normalize(response, mask)
    return total


def _plain_entropy(filled, mask, levels=16, sigma=2.0):
    q = np.clip((filled * levels).astype(np.int64), 0, levels - 1)
    entropy = np.zeros(filled.shape)
    for level in range(levels):
        p = ndimage.gaussian_filter((q == level).astype(np.float64), sigma=(0, sigma, sigma), mode="constant")
        entropy -= np.where(p > 1e-6, p * np.log2(np.maximum(p, 1e-6)), 0.0)
    return np.clip(entropy / np.log2(levels), 0.0, 1.0) * mask


@pytest.mark.parametrize(
    "fast, plain",
    [(channels._symmetry, _plain_symmetry), (channels._orientation, _plain_orientation),
     (channels._entropy, _plain_entropy)],
    ids=["symmetry", "orientation", "entropy"],
)
def test_rewritten_channels_equal_their_plain_formulas(images, fast, plain):
    intensity, mask = images
    filled = channels.fill_background(intensity, mask)
    got, want = fast(filled, mask), plain(filled, mask)
    assert got.shape == want.shape and np.abs(want).max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert got.tobytes() == want.tobytes()


def _plain_curvature(normal, depth, mask, pixel_mm):
    sq = np.zeros(mask.shape)
    for axis in (1, 2):
        dn = (np.roll(normal, -1, axis=axis) - np.roll(normal, 1, axis=axis)) / (2 * pixel_mm)
        jump = np.abs(np.roll(depth, -1, axis=axis) - np.roll(depth, 1, axis=axis))
        ok = mask & np.roll(mask, -1, axis=axis) & np.roll(mask, 1, axis=axis) & (jump < 8 * pixel_mm)
        sq += np.where(ok, (dn * dn).sum(axis=-1), 0.0)
    return channels.masked_blur(np.sqrt(sq / 2), mask, 1.0)


def _plain_edges(normal, depth, mask, pixel_mm):
    far = np.where(mask, depth, depth.max() + 10 * pixel_mm)
    edge = np.zeros(mask.shape)
    for axis in (1, 2):
        for shift in (-1, 1):
            jump = np.abs(np.roll(far, shift, axis=axis) - far) > 4 * pixel_mm
            crease = 1.0 - (np.roll(normal, shift, axis=axis) * normal).sum(axis=-1)
            crease = np.where(np.roll(mask, shift, axis=axis), crease, 0.0)
            edge = np.maximum(edge, np.maximum(jump.astype(np.float64), np.clip(crease, 0.0, 1.0)))
    return channels.masked_blur(edge, mask, 1.0)


@pytest.mark.parametrize(
    "fast, plain", [(channels._curvature, _plain_curvature), (channels._edges, _plain_edges)],
    ids=["curvature", "edges"],
)
def test_geometry_channels_on_object_pixels_equal_their_plain_formulas(images, fast, plain):
    _, mask = images
    rng = np.random.default_rng(3)
    normal = rng.normal(size=(*mask.shape, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    depth = np.where(mask, 50 + 20 * rng.random(mask.shape), 0.0)
    got, want = fast(normal, depth, mask, 1.2), plain(normal, depth, mask, 1.2)
    assert np.abs(want).max() > 0
    assert got.tobytes() == want.tobytes()


def test_wrapped_neighbours_read_as_np_roll():
    mask = np.zeros((2, 5, 7), dtype=bool)
    mask[0, 0, 0] = mask[1, 4, 6] = mask[1, 2, 3] = True
    x = np.arange(2 * 5 * 7, dtype=np.float64).reshape(2, 5, 7)
    pixels = channels._Wrapped(mask, 3)
    flat = pixels.flat(x)
    assert (flat[pixels.here] == x[mask]).all()
    for dy, dx in [(1, 0), (-3, 2), (3, -3), (0, 0)]:
        assert (flat[pixels.at(dy, dx)] == np.roll(x, (-dy, -dx), axis=(1, 2))[mask]).all()
    # (0, 0) of view 0 reads one pixel up as the last row of the same view: [0, 4, 0] = 28.
    assert flat[pixels.at(-1, 0)][0] == 28.0


def test_shared_blurs_equal_separate_masked_blurs(images):
    intensity, mask = images
    blurs = channels._MaskBlur(mask)
    for sigma in (1.0, 2.0, 4.0, 2.0):
        weight = ndimage.gaussian_filter(mask.astype(np.float64), sigma=(0, sigma, sigma), mode="constant")
        value = ndimage.gaussian_filter(intensity * mask, sigma=(0, sigma, sigma), mode="constant")
        want = np.divide(value, weight, out=np.zeros_like(value), where=weight > 1e-3) * mask
        assert blurs(intensity, sigma).tobytes() == want.tobytes()
        assert channels.masked_blur(intensity, mask, sigma).tobytes() == want.tobytes()
    # A constant stays that constant on the object, whatever the mask.
    np.testing.assert_allclose(blurs(np.full(mask.shape, 0.3), 2.0)[mask], 0.3, rtol=1e-12)


def test_benchmark_before_against_the_same_code_agrees_fully(tmp_path, capsys):
    """benchmarks.saliency --before REV with REV's perception equal to the working tree's: every score byte
    equal, every interest point within 5 mm (share 1.0), and both times measured."""
    import json
    import shutil
    import subprocess

    from benchmarks import saliency as bench

    root = Path(bench.__file__).resolve().parents[1]
    if shutil.which("git") is None or subprocess.run(
        ["git", "-C", str(root), "diff", "--quiet", "HEAD", "--", "perception"], check=False, capture_output=True
    ).returncode != 0:
        pytest.skip("needs git and a perception package unchanged since HEAD")
    model = primitives.sphere(40.0, 2)
    (tmp_path / "Ball").mkdir()
    lines = ["OFF", f"{model.n_vertices} {len(model.triangles)} 0"]
    lines += [" ".join(f"{c:.6f}" for c in v) for v in model.vertices]
    lines += ["3 " + " ".join(map(str, t)) for t in model.triangles]
    (tmp_path / "Ball" / "ball.off").write_text("\n".join(lines) + "\n")
    code = bench.main(["--data", str(tmp_path), "--methods", "multiview", "--before", "HEAD", "--json"])
    assert code == 0
    out = capsys.readouterr().out
    result = json.loads(out[out.index("\n{") + 1 :])
    compare = result["before"]
    assert compare["meshes"] == 1 and compare["identical_scores"] == 1
    assert compare["points_within_5mm_mean"] == 1.0 and compare["points_within_5mm_min"] == 1.0
    assert compare["before_median_s"] > 0 and compare["after_median_s"] > 0


def test_blur_within_the_objects_window_equals_the_full_blur(images):
    intensity, mask = images
    for sigma in (1.0, 2.0, 4.0):
        full = ndimage.gaussian_filter(intensity * mask, sigma=(0, sigma, sigma), mode="constant")
        assert channels._blur_object(intensity * mask, mask, sigma).tobytes() == full.tobytes()
    # A small object far from the edges: only its rows and columns widened by the kernel's reach are filtered.
    small = np.zeros((2, 40, 40), dtype=bool)
    small[0, 10:14, 20:23] = small[1, 12:15, 18:20] = True
    assert channels._window(small, 4)[1:] == (slice(6, 19), slice(14, 27))
    assert channels._window(small, 30)[1:] == (slice(0, 40), slice(0, 40))
    assert channels._window(np.zeros((1, 5, 5), dtype=bool), 2)[1:] == (slice(0, 0), slice(0, 0))
    x = small * 2.0
    full = ndimage.gaussian_filter(x, sigma=(0, 1.0, 1.0), mode="constant")
    assert channels._blur_object(x, small, 1.0).tobytes() == full.tobytes()


def test_itti_with_a_mask_equals_itti_of_the_masked_maps(images):
    _, mask = images
    rng = np.random.default_rng(5)
    maps = rng.random(mask.shape) + 3.0 * ~mask  # large values off the object must not count
    got = channels.itti_normalize(maps, mask)
    want = channels.itti_normalize(np.where(mask, maps, 0.0))
    assert got.tobytes() == want.tobytes() and got.max() > 0
    assert not channels.itti_normalize(maps, np.zeros_like(mask)).any()
    # A small object: the normalisation looks within its widened rows and columns only, with the same result.
    small = np.zeros((2, 40, 40), dtype=bool)
    small[0, 10:18, 20:26] = small[1, 12:15, 18:30] = True
    maps = rng.random(small.shape) + 3.0 * ~small
    assert channels._window(small, 3)[1:] == (slice(7, 21), slice(15, 33))
    got = channels.itti_normalize(maps, small)
    assert got.tobytes() == channels.itti_normalize(np.where(small, maps, 0.0)).tobytes() and got.max() > 0


def test_channels_in_threads_equal_each_channel_computed_alone():
    """compute_channels runs its channels side by side in threads: every map is byte for byte the map of that
    channel computed alone, on one thread, and the maps come back in the order asked for."""
    model = _box()
    stack = render_stack(model, width=48, height=40, directions=view_directions(6))
    rng = np.random.default_rng(3)
    color = rng.random(stack.mask.shape + (3,)) * stack.mask[..., None]
    args = (stack.intensity, stack.depth, stack.normal, stack.mask, 1.2)
    names = channels.ALL_CHANNELS[::-1]  # an order unlike the module's
    together = channels.compute_channels(*args, names, color, threads=4)
    assert tuple(together) == names
    assert tuple(channels.compute_channels(*args, names, color, threads=1)) == names
    for name in names:
        alone = channels.compute_channels(*args, (name,), color, threads=1)[name]
        assert alone.any(), name
        assert together[name].tobytes() == alone.tobytes(), name
    with pytest.raises(channels.InvalidArgumentError, match="'dkl' needs colours"):
        channels.compute_channels(*args, ("intensity", "dkl"), None)


@pytest.mark.parametrize("threads,names,workers", [(1, channels.GEOMETRY_CHANNELS, None), (3, channels.GEOMETRY_CHANNELS[:5], 3),
                                                   (8, channels.GEOMETRY_CHANNELS[:2], 2), (4, ("edges",), None)])
def test_channel_threads_follow_the_argument(monkeypatch, threads, names, workers):
    """At most ``threads`` workers and never more than the channels; one thread or one channel makes no pool."""
    made = []
    real = channels.ThreadPoolExecutor

    def recording(*args, max_workers=None, **kwargs):
        made.append(max_workers)
        return real(*args, max_workers=max_workers, **kwargs)

    monkeypatch.setattr(channels, "ThreadPoolExecutor", recording)
    stack = render_stack(_box(), width=32, height=32, directions=view_directions(3))
    channels.compute_channels(stack.intensity, stack.depth, stack.normal, stack.mask, 1.2, names, threads=threads)
    assert made == ([] if workers is None else [workers])
