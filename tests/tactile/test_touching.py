"""Touching an object along K contours: the two seed schemes give exactly the contours and frames their
definitions say, whoever calls them (explore_object, touch_object, recognize, the dataset worker)."""

from __future__ import annotations

import zlib
from fractions import Fraction

import numpy as np
import pytest

from fusion.experiments.touch import touch_object
from perception.errors import InvalidArgumentError
from perception.shapes import make_object
from tactile.contours import make_contour, plane_through
from tactile.explore import explore
from tactile.sensor import FSRSensor
from tactile.touching import SPARE_PLANES, Toucher, TouchTiming, explore_object, touch, touch_variants

SENSOR = FSRSensor(rows=8, cols=8)
NOISY = FSRSensor(rows=8, cols=8, noise_std=0.05, dead_taxel_rate=0.05)


@pytest.fixture(scope="module")
def box():
    return make_object("box", 1)


def _plane(model, rng):
    """Two distinct random vertices and the plane through them and the centre (what 'blind' draws)."""
    i, j = rng.choice(model.n_vertices, size=2, replace=False)
    return plane_through(model.center, model.vertices[i], model.vertices[j])


def _assert_same(a, b):
    for name in ("frames", "normals", "positions", "tangents", "pad_sides_mm"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.seed == b.seed and a.strategy == b.strategy


class TestStreamSeeding:
    def test_known_noise_seeds(self, box):
        """The noise seeds drawn for seed 7 are fixed numbers: a change of the stream changes the data."""
        sequences = explore_object(box, "blind", 3, SENSOR, 10, seed=7)
        assert [s.seed for s in sequences] == [1926751965, 483628757, 1875941738]

    @pytest.mark.parametrize("sensor", [SENSOR, NOISY], ids=["clean", "noisy"])
    def test_each_contour_is_a_plane_then_a_noise_seed_from_one_generator(self, box, sensor):
        """Contour k: two vertices drawn from default_rng(seed), cut at 10 probes, then its noise seed."""
        rng = np.random.default_rng(7)
        expected = []
        for _ in range(3):
            contour = make_contour(box, _plane(box, rng), 10)  # a box: every plane through the centre cuts it
            expected.append(explore(box, contour, sensor, seed=int(rng.integers(2**31 - 1)), strategy="blind"))
        for got, want in zip(touch(box, "blind", 3, sensor, 10, seed=7), expected):
            _assert_same(got, want)
        for got, want in zip(explore_object(box, "blind", 3, sensor, 10, seed=7), expected):
            _assert_same(got, want)

    def test_a_store_row_is_the_first_contour_of_its_own_seed(self, box):
        """The dataset worker's per-contour draw is the stream scheme with n=1."""
        toucher = Toucher(box, "blind", probes=10)
        (planned,) = toucher.stream(1, 12345)
        (sequence,) = touch(box, "blind", 1, NOISY, 10, seed=12345)
        assert planned.noise_seed == sequence.seed
        np.testing.assert_array_equal(planned.contour.positions, sequence.positions)


class TestObjectSeeding:
    def test_known_noise_seeds(self, box):
        sequences, _ = touch_object(box, "blind", 3, sensor=SENSOR, probes=10, seed=7)
        assert [s.seed for s in sequences] == [1686718773, 1762783595, 1440013262]

    @pytest.mark.parametrize("sensor", [SENSOR, NOISY], ids=["clean", "noisy"])
    def test_planes_noise_and_jitter_come_from_three_streams_of_the_object_seed(self, box, sensor):
        """(seed, crc32(name), crc32(strategy)) spawns planes (K + spare drawn at once), noise seeds, jitter."""
        plane_seed, noise_seed, _ = np.random.SeedSequence(
            [7, zlib.crc32(box.name.encode()), zlib.crc32(b"blind")]).spawn(3)
        rng = np.random.default_rng(plane_seed)
        planes = [_plane(box, rng) for _ in range(3 + SPARE_PLANES)]
        seeds = np.random.default_rng(noise_seed).integers(2**31 - 1, size=len(planes))
        expected = [explore(box, make_contour(box, p, 10), sensor, seed=int(s), strategy="blind")
                    for p, s in zip(planes[:3], seeds[:3])]
        got, contours = touch_object(box, "blind", 3, sensor=sensor, probes=10, seed=7)
        same = touch(box, "blind", 3, sensor, 10, 7, seeding="object")
        for a, b, want in zip(got, same, expected):
            _assert_same(a, want)
            _assert_same(b, want)
        assert [c.plane.normal.tolist() for c in contours] == [p.normal.tolist() for p in planes[:3]]

    def test_blind_skips_planes_that_miss_and_keeps_each_plane_s_noise_seed(self, box, monkeypatch):
        """Blind planes that miss are skipped: the contours are planes 1, 3, 4 of the 3 + SPARE_PLANES drawn and
        their noise seeds are those planes' seeds (indexed by plane); when too few cut, ContourError says so."""
        from perception.errors import ContourError

        plane_seed, noise_seed, _ = np.random.SeedSequence(
            [7, zlib.crc32(box.name.encode()), zlib.crc32(b"blind")]).spawn(3)
        rng = np.random.default_rng(plane_seed)
        planes = [_plane(box, rng) for _ in range(3 + SPARE_PLANES)]
        seeds = np.random.default_rng(noise_seed).integers(2**31 - 1, size=len(planes))
        toucher = Toucher(box, "blind", probes=10)
        cut = toucher.cut

        def missing(*which):
            gone = {planes[i].normal.tobytes() for i in which}

            def fake(plane):
                if plane.normal.tobytes() in gone:
                    raise ContourError("misses")
                return cut(plane)
            return fake

        monkeypatch.setattr(toucher, "cut", missing(0, 2))
        planned, _ = toucher.by_object(3, 7)
        planned = list(planned)
        assert [p.contour.plane.normal.tolist() for p in planned] == [planes[i].normal.tolist() for i in (1, 3, 4)]
        assert [p.noise_seed for p in planned] == [int(seeds[i]) for i in (1, 3, 4)]
        monkeypatch.setattr(toucher, "cut", missing(0, *range(2, len(planes))))
        planned, _ = toucher.by_object(3, 7)
        with pytest.raises(ContourError, match="only 1 of 3"):
            list(planned)

    def test_jitter_moves_the_press_not_the_plan(self, box):
        """Jittered touches press elsewhere but record the planned poses of the same contours."""
        clean = touch(box, "blind", 3, SENSOR, 10, 7, seeding="object")
        moved = touch(box, "blind", 3, SENSOR, 10, 7, seeding="object", jitter_mm=2.0)
        for a, b in zip(clean, moved):
            np.testing.assert_array_equal(a.positions, b.positions)
            assert a.seed == b.seed
        assert any(not np.array_equal(a.frames, b.frames) for a, b in zip(clean, moved))


class TestArguments:
    def test_unknown_seeding_is_refused(self, box):
        with pytest.raises(InvalidArgumentError, match="seeding"):
            touch(box, "blind", 1, seeding="sometimes")

    def test_more_sequences_than_memory_holds_are_refused_before_touching(self, box, monkeypatch):
        # 1,100 contours x 25 probes x (32 x 32 x 4 + 40) bytes = 113,740,000 B = 108.5 MiB, above a 100 MiB limit;
        # 1,000 (98.6 MiB) would fit.
        monkeypatch.setenv("VISUOTACTILE_MAX_MEMORY_MB", "100")
        with pytest.raises(InvalidArgumentError, match=r"touching 1100 contours.*108 MB.*limit of 100 MB"):
            touch(box, "blind", 1100, FSRSensor(), 25, 0)
        from perception.limits import check_bytes

        assert check_bytes(1000 * 25 * (32 * 32 * 4 + 40), "1000 contours") == 103_400_000

    def test_stream_jitter_leaves_the_contours(self, box):
        """Jitter in the stream scheme has its own generator: the planned contours do not move."""
        clean = touch(box, "blind", 2, SENSOR, 10, 3)
        moved = touch(box, "blind", 2, SENSOR, 10, 3, jitter_mm=1.0)
        for a, b in zip(clean, moved):
            np.testing.assert_array_equal(a.positions, b.positions)


class TestGivenPlanes:
    def test_touches_the_given_planes_in_order(self, box):
        """A policy's planes are touched as given: the same contours as cutting them directly, noise seeds from
        the seed's stream."""
        planes = [plane_through(box.center, box.vertices[0], box.vertices[v]) for v in (5, 40)]
        sequences = touch(box, "blind", 2, SENSOR, 10, 3, planes=planes)
        rng = np.random.default_rng(3)
        for sequence, plane in zip(sequences, planes):
            expected = explore(box, make_contour(box, plane, 10), SENSOR, seed=int(rng.integers(2**31 - 1)))
            np.testing.assert_array_equal(sequence.frames, expected.frames)
            np.testing.assert_array_equal(sequence.plane.normal, plane.normal)

    def test_noise_seeds_come_from_the_seed_in_turn(self, box):
        """Each contour's noise seed is the next integer below 2**31 - 1 drawn from the seed's generator: recorded
        with the sequence and giving a noisy sensor's frames."""
        planes = [plane_through(box.center, box.vertices[0], box.vertices[v]) for v in (5, 40, 77)]
        sequences = touch(box, "blind", 3, NOISY, 10, 11, planes=planes)
        rng = np.random.default_rng(11)
        for sequence, plane in zip(sequences, planes, strict=True):
            noise = int(rng.integers(2**31 - 1))
            assert sequence.seed == noise
            np.testing.assert_array_equal(sequence.frames, explore(box, make_contour(box, plane, 10), NOISY,
                                                                   seed=noise).frames)

    def test_count_must_match(self, box):
        plane = plane_through(box.center, box.vertices[0], box.vertices[5])
        with pytest.raises(InvalidArgumentError, match="1 planes given for n_contours=2"):
            touch(box, "blind", 2, SENSOR, 10, 3, planes=[plane])

    def test_what_is_not_a_plane_is_refused_before_the_saliency(self, box, monkeypatch):
        """touch(planes=[None]) raised AttributeError, after the guided strategy's saliency."""
        from perception import saliency

        monkeypatch.setattr(saliency, "saliency", lambda *a, **k: pytest.fail("saliency computed"))
        with pytest.raises(InvalidArgumentError, match=f"^{box.name}: plane 0 must be a tactile.contours.Plane"):
            touch(box, "guided", 1, SENSOR, 10, 3, planes=[None])
        with pytest.raises(InvalidArgumentError, match=f"^{box.name}: planes must be an iterable"):
            touch(box, "guided", 1, SENSOR, 10, 3, planes=7)


class TestVariants:
    """touch_variants: several (seed, jitter) touches of the same planes, cut once and pressed in one pass."""

    @pytest.mark.parametrize("sensor", [SENSOR, NOISY], ids=["clean", "noisy"])
    def test_each_variant_is_what_touch_gives(self, box, sensor):
        planes = [plane_through(box.center, box.vertices[0], box.vertices[v]) for v in (5, 40, 77)]
        variants = [(3, 0.0), (4, 1.0), (9, 2.5)]
        got = touch_variants(Toucher(box, "blind", probes=10), planes, sensor, variants)
        assert [len(g) for g in got] == [3, 3, 3]
        for (seed, jitter), sequences in zip(variants, got):
            expected = touch(box, "blind", 3, sensor, 10, seed, planes=planes, jitter_mm=jitter)
            for a, b in zip(sequences, expected, strict=True):
                np.testing.assert_array_equal(a.frames, b.frames)
                np.testing.assert_array_equal(a.pad_sides_mm, b.pad_sides_mm)
                np.testing.assert_array_equal(a.positions, b.positions)  # the planned poses, jitter or not
                assert (a.seed, a.strategy, a.object_name) == (b.seed, b.strategy, b.object_name)
        # jitter moves the presses: the jittered variants read other frames than the planned one
        assert not np.array_equal(got[0][0].frames, got[1][0].frames)

    def test_a_guided_toucher_gives_what_touch_gives_for_its_strategy(self, box):
        planes = [plane_through(box.center, box.vertices[0], box.vertices[v]) for v in (5, 40)]
        variants = [(0, 0.0), (6, 1.5)]
        got = touch_variants(Toucher(box, "guided", probes=10), planes, NOISY, variants)
        for (seed, jitter), sequences in zip(variants, got, strict=True):
            expected = touch(box, "guided", 2, NOISY, 10, seed, planes=planes, jitter_mm=jitter)
            for a, b in zip(sequences, expected, strict=True):
                np.testing.assert_array_equal(a.frames, b.frames)
                assert (a.seed, a.strategy) == (b.seed, "guided")

    def test_more_than_memory_holds_is_refused_before_cutting(self, box, monkeypatch):
        """355 sequences of 10 probes on 8 x 8 taxels (2,960 B each: 1,050,800 B) are above a 1 MB limit; the
        variants count, not only the planes."""
        from tactile import touching

        monkeypatch.setenv("VISUOTACTILE_MAX_MEMORY_MB", "1")
        monkeypatch.setattr(touching, "make_contour", lambda *a, **k: pytest.fail("a plane was cut"))
        plane = plane_through(box.center, box.vertices[0], box.vertices[5])
        with pytest.raises(InvalidArgumentError, match=r"^box/1: touching 355 contours .*limit of 1 MB"):
            touch_variants(Toucher(box, "blind", probes=10), [plane] * 5, SENSOR, [(k, 0.0) for k in range(71)])

    def test_planes_are_cut_once(self, box, monkeypatch):
        from tactile import touching

        cuts = []
        real = touching.make_contour
        monkeypatch.setattr(touching, "make_contour", lambda *a, **k: cuts.append(1) or real(*a, **k))
        planes = [plane_through(box.center, box.vertices[0], box.vertices[v]) for v in (5, 40)]
        touch_variants(Toucher(box, "blind", probes=10), planes, SENSOR, [(0, 0.0), (1, 1.0), (2, 1.0)])
        assert len(cuts) == 2

    @pytest.mark.parametrize("variants, match", [
        ([], "at least one plane and one variant"),
        ([(0,)], "a variant must be"),
        ([3], "a variant must be"),
        ([(-1, 0.0)], "seed"),
        ([(1.5, 0.0)], "seed"),
        ([(np.random.default_rng(0), 0.0)], "must be an integer"),
        ([(0, 0.0, 1)], "a variant must be"),
        ([(0, -1.0)], "jitter"),
        ([(0, float("nan"))], "jitter"),
    ])
    def test_bad_variants_are_refused(self, box, variants, match):
        plane = plane_through(box.center, box.vertices[0], box.vertices[5])
        with pytest.raises(InvalidArgumentError, match=match):
            touch_variants(Toucher(box, "blind", probes=10), [plane], SENSOR, variants)

    def test_bad_arguments_are_refused(self, box):
        plane = plane_through(box.center, box.vertices[0], box.vertices[5])
        with pytest.raises(InvalidArgumentError, match="Toucher"):
            touch_variants(box, [plane], SENSOR, [(0, 0.0)])
        with pytest.raises(InvalidArgumentError, match="FSRSensor"):
            touch_variants(Toucher(box, "blind", probes=10), [plane], "sensor", [(0, 0.0)])
        with pytest.raises(InvalidArgumentError, match="at least one plane"):
            touch_variants(Toucher(box, "blind", probes=10), [], SENSOR, [(0, 0.0)])

    @pytest.mark.parametrize("planes, variants, match", [
        (None, [(0, 0.0)], "planes must be an iterable of tactile.contours.Plane, got NoneType"),
        ([None], [(0, 0.0)], "plane 0 must be a tactile.contours.Plane, got NoneType"),
        ("plane", [(0, 0.0)], "plane 0 must be a tactile.contours.Plane, got str"),
        ("good+pair", [(0, 0.0)], "plane 1 must be a tactile.contours.Plane, got tuple"),
        ("good", None, "variants must be an iterable of .seed, jitter_mm., got NoneType"),
        ("good", 5, "variants must be an iterable"),
    ])
    def test_what_is_not_planes_or_variants_is_refused_by_name(self, box, planes, variants, match):
        """None, a (point, normal) pair or a non-iterable raised AttributeError or TypeError."""
        good = plane_through(box.center, box.vertices[0], box.vertices[5])
        named = {"good": [good], "good+pair": [good, (good.point, good.normal)]}
        planes = named.get(planes, planes) if isinstance(planes, str) else planes
        with pytest.raises(InvalidArgumentError, match=f"^{box.name}: {match}"):
            touch_variants(Toucher(box, "blind", probes=10), planes, SENSOR, variants)

    @pytest.mark.parametrize("jitter", [10**400, Fraction(-1, 2), "1", True, float("inf"), 1000.5, 1e308])
    def test_jitter_that_is_no_length_is_refused_by_name(self, box, jitter):
        """An integer beyond the float range raised numpy's TypeError from isfinite; 1e308 mm ended in NaN probe
        positions (after numpy's overflow warnings): beyond MAX_JITTER_MM (1 m) a finger touches no object."""
        plane = plane_through(box.center, box.vertices[0], box.vertices[5])
        with pytest.raises(InvalidArgumentError, match=rf"^{box.name}: pose jitter must be a finite number in \[0, 1000\] mm"):
            touch_variants(Toucher(box, "blind", probes=10), [plane], SENSOR, [(0, jitter)])
        with pytest.raises(InvalidArgumentError, match=rf"^{box.name}: pose jitter must be a finite number in \[0, 1000\] mm"):
            touch(box, "blind", 1, SENSOR, 10, 0, planes=[plane], jitter_mm=jitter)

    def test_a_fraction_of_a_millimetre_is_a_jitter(self, box):
        plane = plane_through(box.center, box.vertices[0], box.vertices[5])
        (got,) = touch_variants(Toucher(box, "blind", probes=10), [plane], SENSOR, [(2, Fraction(1, 2))])
        (expected,) = touch(box, "blind", 1, SENSOR, 10, 2, planes=[plane], jitter_mm=0.5)
        np.testing.assert_array_equal(got[0].frames, expected.frames)

    def test_planes_from_a_generator(self, box):
        """Planes may come from any iterable: a generator is read once, and touch() takes one too."""
        planes = [plane_through(box.center, box.vertices[0], box.vertices[v]) for v in (5, 40)]
        got = touch_variants(Toucher(box, "blind", probes=10), (p for p in planes), SENSOR, [(1, 0.0), (2, 1.0)])
        assert [len(g) for g in got] == [2, 2]
        for (seed, jitter), sequences in zip([(1, 0.0), (2, 1.0)], got):
            expected = touch(box, "blind", 2, SENSOR, 10, seed, planes=iter(planes), jitter_mm=jitter)
            for a, b in zip(sequences, expected, strict=True):
                np.testing.assert_array_equal(a.frames, b.frames)

    def test_more_than_the_contour_limit_is_refused_before_cutting(self, box, monkeypatch):
        monkeypatch.setenv("VISUOTACTILE_MAX_CONTOURS", "5")
        plane = plane_through(box.center, box.vertices[0], box.vertices[5])
        with pytest.raises(InvalidArgumentError, match="contours"):
            touch_variants(Toucher(box, "blind", probes=10), [plane] * 3, SENSOR, [(0, 0.0), (1, 0.0)])


@pytest.mark.parametrize("sensor", [FSRSensor(rows=16, cols=16, noise_std=0.05, dead_taxel_rate=0.1),
                                    FSRSensor(rows=16, cols=16)], ids=["noisy", "clean"])
def test_touch_presses_in_one_pass_what_one_press_per_contour_gives(sensor):
    """touch() presses its contours together; each sequence equals FSRSensor.press of that contour alone with
    its noise seed, bit for bit (a mug: its handle makes pads shrink and settle), timed or not."""
    from perception.errors import SensorSpecError

    mug = make_object("mug", 1)
    contours = []
    sequences = touch(mug, "blind", 6, sensor, probes=12, seed=4, contours=contours)
    shrunk = 0
    for seq, contour in zip(sequences, contours):
        frames, sides = sensor.press(mug, contour.positions, contour.normals, contour.tangents, seed=seq.seed)
        np.testing.assert_array_equal(seq.frames, frames)
        np.testing.assert_array_equal(seq.pad_sides_mm, sides)
        shrunk += int((sides < sensor.side_mm).sum())
    assert shrunk > 0  # the adaptation ran
    timed = touch(mug, "blind", 6, sensor, probes=12, seed=4, timing=TouchTiming())
    for a, b in zip(sequences, timed):
        np.testing.assert_array_equal(a.frames, b.frames)
    with pytest.raises(SensorSpecError, match="2 seeds for 1 contours"):
        sensor.press_contours(mug, contours[:1], [1, 2])
    empty = type("Empty", (), {"positions": np.zeros((0, 3)), "normals": np.zeros((0, 3)), "tangents": np.zeros((0, 3))})
    with pytest.raises(SensorSpecError, match="contour 1 has no probes"):
        sensor.press_contours(mug, [contours[0], empty], [1, 2])


@pytest.mark.parametrize("noisy", [FSRSensor(rows=16, cols=16, noise_std=0.3), FSRSensor(rows=16, cols=16, dead_taxel_rate=0.2),
                                   FSRSensor(rows=16, cols=16, noise_std=1.0, dead_taxel_rate=0.05)],
                         ids=["taxel-noise", "dead-taxels", "both"])
def test_reread_gives_what_pressing_with_the_noisy_sensor_gives(noisy):
    """Read-out noise does not move the pads: re-reading a clean touch's frames with each sequence's seed gives
    the noisy sensor's touch bit for bit (a mug, so pads shrink and settle), and leaves the clean frames alone."""
    mug = make_object("mug", 1)
    clean = touch(mug, "blind", 4, FSRSensor(rows=16, cols=16), probes=10, seed=9)
    noisy_touch = touch(mug, "blind", 4, noisy, probes=10, seed=9)
    for c, n in zip(clean, noisy_touch):
        before = c.frames.copy()
        reread = noisy.reread(c.frames, c.seed)
        assert reread.dtype == np.float32
        np.testing.assert_array_equal(reread, n.frames)
        np.testing.assert_array_equal(c.frames, before)
        assert not np.array_equal(reread, c.frames)


def test_reread_refuses_what_is_not_a_clean_gap_reading():
    from perception.errors import SensorSpecError

    frames = np.full((3, 8, 8), 2.0, dtype=np.float32)
    sensor = FSRSensor(rows=8, cols=8, noise_std=0.1)
    np.testing.assert_array_equal(FSRSensor(rows=8, cols=8).reread(frames, 1), frames)  # no noise: unchanged
    with pytest.raises(SensorSpecError, match="gap mode|gap-mode"):
        FSRSensor(rows=8, cols=8, mode="contact").reread(frames, 1)
    with pytest.raises(SensorSpecError, match=r"\(P, 8, 8\)"):
        sensor.reread(frames[:, :4], 1)
    with pytest.raises(SensorSpecError, match=r"\(P, 8, 8\)"):
        sensor.reread(frames[:, :, :4], 1)
    with pytest.raises(SensorSpecError, match=r"\(P, 8, 8\)"):
        sensor.reread(frames[:0], 1)
    for bad in (np.nan, -0.5, 10.5):
        broken = frames.copy()
        broken[1, 2, 3] = bad
        with pytest.raises(SensorSpecError, match=r"\[0, 10\] mm"):
            sensor.reread(broken, 1)
    with pytest.raises(SensorSpecError):
        sensor.reread(frames, -3)


def test_a_touch_that_meets_nothing_is_warned_about(caplog):
    """A mug 0.5 mm across (a mesh in metres loaded without rescaling) under a 20 mm pad: no ray meets it, every frame
    reads the range, and the user is told why instead of getting blank frames in silence."""
    import logging

    from perception.geometry import rescale
    from perception.shapes import make_object
    from tactile import touch

    tiny = rescale(make_object("mug", seed=3), size_mm=0.5, name="tiny mug")
    with caplog.at_level(logging.WARNING, logger="tactile.sensor"):
        sequences = touch(tiny, "blind", 2, probes=5, seed=0)
    assert all((s.frames == 10.0).all() for s in sequences)
    (record,) = [r for r in caplog.records if "touched nothing" in r.getMessage()]
    assert record.getMessage().startswith("tiny mug: 10 of 10 presses touched nothing") and "0.5 mm across" in \
        record.getMessage()

    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="tactile.sensor"):
        touch(make_object("mug", seed=3), "blind", 2, probes=5, seed=0)
    assert not [r for r in caplog.records if "touched nothing" in r.getMessage()]


def test_rays_are_counted_and_recorded(tmp_path):
    """``rays_cast`` counts one ray per taxel of every pad cast (12 pads of 8 x 6 taxels: 576); a store's record
    holds its object's rays, at least one full pad per stored probe (blind contours are all distinct) and more where
    the adaptive pad surveys, shrinks or settles."""
    import json

    from perception.shapes import make_object
    from tactile.dataset import generate
    from tactile.sensor import FSRSensor, rays_cast

    box = make_object("box", seed=0)
    sensor = FSRSensor(rows=8, cols=6)
    positions = box.center + np.array([[0.0, 0.0, 200.0]]) * np.ones((12, 1))
    normals = np.tile([0.0, 0.0, 1.0], (12, 1))
    tangents = np.tile([1.0, 0.0, 0.0], (12, 1))
    before = rays_cast()
    sensor.measure_gaps(box, positions, normals, tangents, np.full(12, 10.0))
    assert rays_cast() - before == 12 * 8 * 6

    generate([("box", 0)], tmp_path / "s.zarr", strategies=("blind",), contours_per_object=4, probes=5,
             sensor=sensor, workers=1, progress=False)
    record = json.loads((tmp_path / "s.zarr" / "records" / "00000.json").read_text())
    assert record["rays"] > 4 * 5 * 8 * 6, record["rays"]  # the survey pass comes first

    # each record counts its own object's rays: the can after the box in one worker, as the can alone
    settings = {"strategies": ("blind",), "contours_per_object": 4, "probes": 5, "sensor": sensor, "workers": 1,
                "progress": False}
    generate([("box", 0), ("can", 0)], tmp_path / "two.zarr", **settings)
    generate([("can", 0)], tmp_path / "can.zarr", **settings)
    after_box = json.loads((tmp_path / "two.zarr" / "records" / "00001.json").read_text())["rays"]
    assert after_box == json.loads((tmp_path / "can.zarr" / "records" / "00000.json").read_text())["rays"]
