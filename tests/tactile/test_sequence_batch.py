"""SequenceBatch: stacking explored sequences and checking shapes."""

from __future__ import annotations

import numpy as np
import pytest

from perception import primitives
from perception.errors import DatasetError
from tactile import FSRSensor, SequenceBatch, explore, make_contour, plane_through


@pytest.fixture(scope="module")
def sequences():
    sensor = FSRSensor(rows=8, cols=8)
    out = []
    for name, label, radius in (("s1", "ball", 30.0), ("s2", "ball", 40.0), ("s3", "box", 30.0)):
        model = primitives.sphere(radius, 2)
        object.__setattr__(model, "name", name)
        object.__setattr__(model, "label", label)
        contour = make_contour(model, plane_through([0, 0, 0], [1, 0, 0], [0, 1, 0.3]), 9)
        out.append(explore(model, contour, sensor, seed=1))
    return out


def test_stacks_sequences_with_labels_and_objects(sequences):
    batch = SequenceBatch.from_sequences(sequences, sensor_spec=FSRSensor(rows=8, cols=8).spec())
    assert len(batch) == 3 and batch.n_probes == 9 and batch.grid == (8, 8)
    assert batch.class_names == ("ball", "box") and list(batch.labels) == [0, 0, 1]
    assert batch.object_names == ("s1", "s2", "s3") and list(batch.object_ids) == [0, 1, 2]
    np.testing.assert_array_equal(batch.frames[2], sequences[2].frames)
    np.testing.assert_allclose(batch.plane_normals[0], sequences[0].plane.normal)
    sub = batch.subset(np.array([2, 0]))
    assert list(sub.labels) == [1, 0] and sub.class_names == batch.class_names


def test_unknown_labels_and_mixed_shapes_are_refused(sequences):
    with pytest.raises(DatasetError, match="not in"):
        SequenceBatch.from_sequences(sequences, class_names=["ball"])
    with pytest.raises(DatasetError, match="no sequences"):
        SequenceBatch.from_sequences([])
    batch = SequenceBatch.from_sequences(sequences)
    with pytest.raises(DatasetError, match="normals must have shape"):
        SequenceBatch(**{**batch.__dict__, "normals": batch.normals[:, :3]})


def test_concatenate_joins_sequences_and_object_lists(sequences):
    spec = FSRSensor(rows=8, cols=8).spec()
    classes = ["ball", "box"]
    first = SequenceBatch.from_sequences(sequences[:2], class_names=classes, sensor_spec=spec)
    second = SequenceBatch.from_sequences([sequences[2], sequences[0]], class_names=classes, sensor_spec=spec)
    joined = SequenceBatch.concatenate([first, second])
    assert len(joined) == 4 and joined.class_names == ("ball", "box")
    # s1 appears in both batches: one name, one id; s3 is new and numbered after the first batch's objects.
    assert joined.object_names == ("s1", "s2", "s3") and list(joined.object_ids) == [0, 1, 2, 0]
    assert list(joined.labels) == [0, 0, 1, 0]
    for row, seq in zip(range(4), [sequences[0], sequences[1], sequences[2], sequences[0]]):
        np.testing.assert_array_equal(joined.frames[row], seq.frames)
        np.testing.assert_array_equal(joined.plane_points[row], seq.plane.point)
    assert joined.sensor_spec == spec


def test_concatenate_refuses_batches_that_do_not_match(sequences):
    spec = FSRSensor(rows=8, cols=8).spec()
    batch = SequenceBatch.from_sequences(sequences, class_names=["ball", "box"], sensor_spec=spec)
    with pytest.raises(DatasetError, match="no batches"):
        SequenceBatch.concatenate([])
    with pytest.raises(DatasetError, match="classes"):
        SequenceBatch.concatenate([batch, SequenceBatch.from_sequences(sequences, class_names=["box", "ball"],
                                                                       sensor_spec=spec)])
    with pytest.raises(DatasetError, match="another sensor"):
        SequenceBatch.concatenate([batch, SequenceBatch.from_sequences(sequences, class_names=["ball", "box"],
                                                                       sensor_spec=FSRSensor(rows=8, cols=8,
                                                                                             noise_std=0.1).spec())])
    with pytest.raises(DatasetError, match="shape"):
        SequenceBatch.concatenate([batch, SequenceBatch(
            **{**batch.__dict__, "frames": batch.frames[:, :5], "normals": batch.normals[:, :5],
               "positions": batch.positions[:, :5], "tangents": batch.tangents[:, :5],
               "pad_sides_mm": batch.pad_sides_mm[:, :5]})])


def test_concatenate_keeps_the_first_batch_and_numbers_new_objects_in_order(sequences):
    spec = FSRSensor(rows=8, cols=8).spec()
    make = lambda s: SequenceBatch.from_sequences(s, class_names=["ball", "box"], sensor_spec=spec)
    s1, s2, s3 = sequences
    joined = SequenceBatch.concatenate([make([s3, s1]), make([s2, s3])])
    assert joined.object_names == ("s3", "s1", "s2")  # the first batch's ids still hold; s2 comes after
    assert list(joined.object_ids) == [0, 1, 2, 0]


def test_concatenate_with_empty_batches(sequences):
    spec = FSRSensor(rows=8, cols=8).spec()
    full = SequenceBatch.from_sequences([sequences[0], sequences[2]], class_names=["ball", "box"], sensor_spec=spec)
    empty = full.subset(np.zeros(0, dtype=np.int64))
    assert len(SequenceBatch.concatenate([empty, empty])) == 0
    for joined in (SequenceBatch.concatenate([empty, full]), SequenceBatch.concatenate([full, empty])):
        names = np.asarray(joined.object_names, dtype=object)[joined.object_ids]
        assert len(joined) == 2 and list(names) == ["s1", "s3"]
        np.testing.assert_array_equal(joined.frames, full.frames)


def test_concatenate_refuses_what_is_not_a_list_of_batches(sequences):
    batch = SequenceBatch.from_sequences(sequences)
    for bad in ([1, batch], [batch, None], [batch, sequences[0]], (b for b in [batch]), batch, None):
        with pytest.raises(DatasetError, match="concatenate"):
            SequenceBatch.concatenate(bad)
    broken = SequenceBatch(**{**batch.__dict__, "object_ids": np.array([0, 1, 7])})
    with pytest.raises(DatasetError, match="object ids outside"):
        SequenceBatch.concatenate([batch, broken])


def test_concatenate_keeps_the_first_batch_dtypes(sequences):
    batch = SequenceBatch.from_sequences(sequences)
    wide = SequenceBatch(**{**batch.__dict__, "frames": batch.frames.astype(np.float64)})
    joined = SequenceBatch.concatenate([batch, wide])
    assert joined.frames.dtype == np.float32 and len(joined) == 6
