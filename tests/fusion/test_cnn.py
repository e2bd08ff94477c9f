"""CNN pair: nets, preprocessing, training, fusion, determinism, persistence, numerics."""

from __future__ import annotations

import contextlib
import copy

import numpy as np
import pytest
import torch

import fusion.cnn as cnn_module
from fusion.base import load_model
from fusion.cnn import (
    CNNClassifier,
    CutaneousNet,
    KinestheticNet,
    _circular_probes,
    fuse_modalities,
    pool_frames,
)
from fusion.cues import kinesthetic_cues
from fusion.modelfile import read_model_file, write_model_file
from perception.errors import DatasetError, InvalidArgumentError, ModelFileError, ModelMismatchError
from tactile.explore import SequenceBatch
from tactile.sensor import FSRSensor

SPEC = FSRSensor(rows=8, cols=8).spec()
FAST = {"epochs": 12, "batch_size": 16, "lr": 3e-3, "patience": 100, "progress": False, "threads": 1}


def make_batch(n_per_class=16, probes=5, grid=(8, 8), n_classes=3, informative=("cutaneous", "kinesthetic"),
               seed=0, spec=SPEC) -> SequenceBatch:
    """Synthetic sequences whose class shows in the frames (a raised band of rows) and/or the normals (near
    one axis per class); an uninformative modality is the same noise for every class."""
    rng = np.random.default_rng(seed)
    s = n_per_class * n_classes
    labels = np.repeat(np.arange(n_classes), n_per_class)
    frames = rng.uniform(0.0, 2.0, (s, probes) + grid).astype(np.float32)
    normals = rng.normal(size=(s, probes, 3))
    if "cutaneous" in informative:
        band = np.array_split(np.arange(grid[0]), n_classes)
        for i, c in enumerate(labels):
            frames[i, :, band[c], :] += 6.0
    if "kinesthetic" in informative:
        normals = 0.3 * normals + 3.0 * np.eye(3)[labels % 3][:, None, :]
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    angle = np.linspace(0, 2 * np.pi, probes, endpoint=False)
    positions = np.stack([50 * np.cos(angle), 50 * np.sin(angle), np.zeros(probes)], -1)
    tangents = np.stack([-np.sin(angle), np.cos(angle), np.zeros(probes)], -1)
    return SequenceBatch(
        frames=frames, normals=normals.astype(np.float32),
        positions=np.broadcast_to(positions, (s, probes, 3)).astype(np.float32),
        tangents=np.broadcast_to(tangents, (s, probes, 3)).astype(np.float32),
        pad_sides_mm=np.full((s, probes), 20.0, np.float32), plane_points=np.zeros((s, 3)),
        plane_normals=np.tile([0.0, 0.0, 1.0], (s, 1)), labels=labels, object_ids=labels.copy(),
        class_names=tuple(f"class{c}" for c in range(n_classes)),
        object_names=tuple(f"object{c}" for c in range(n_classes)), sensor_spec=spec,
    )


def accuracy(model, batch, modality="fusion") -> float:
    proba = model.predict_proba_modalities(batch)[modality]
    names = np.asarray(batch.class_names)[batch.labels]
    return float(np.mean(model.classes_[proba.argmax(1)] == names))


# ------------------------------------------------------------------------------------------ the nets
@pytest.mark.parametrize("probes,grid", [(1, (1, 1)), (7, (5, 9)), (25, (32, 32)), (4, (3, 16))])
def test_nets_take_any_probe_count_and_grid(probes, grid):
    x = torch.zeros((2, 1, probes) + grid)
    assert CutaneousNet(probes, grid, 5).eval()(x).shape == (2, 5)
    assert KinestheticNet(probes, 6, 2).eval()(torch.zeros(3, 1, probes, 6)).shape == (3, 2)


def test_circular_padding_wraps_the_probe_axis():
    x = torch.arange(5.0).view(1, 1, 5, 1)
    assert _circular_probes(x).flatten().tolist() == [4, 0, 1, 2, 3, 4, 0]


def test_convolutions_are_equivariant_to_cyclic_shifts_of_the_probes():
    # A closed contour has no first probe: shifting the input's probes shifts the conv features the same.
    torch.manual_seed(0)
    net = CutaneousNet(9, (8, 8), 3).eval()
    x = torch.randn(2, 1, 9, 8, 8)

    def features(v):
        v = torch.relu(net.bn1(net.conv1(_circular_probes(v))))
        return torch.relu(net.bn2(net.conv2(_circular_probes(v))))

    with torch.no_grad():
        torch.testing.assert_close(features(torch.roll(x, 3, 2)), torch.roll(features(x), 3, 2))


def test_pool_frames_averages_blocks_and_keeps_small_grids():
    rng = np.random.default_rng(1)
    frames = rng.uniform(0, 10, (3, 4, 32, 32)).astype(np.float32)
    expected = frames.reshape(3, 4, 16, 2, 16, 2).mean(axis=(3, 5))
    np.testing.assert_allclose(pool_frames(frames, 16).numpy(), expected, rtol=1e-5)
    small = frames[:, :, :8, :12]
    np.testing.assert_array_equal(pool_frames(small, 16).numpy(), small)


# ------------------------------------------------------------------------------------ augmentation
def test_reversing_a_contour_rotates_each_frame_by_180_degrees():
    # The augmentation's assumption, checked against the sensor: press the probes in the reverse order with
    # reversed tangents and each frame comes out turned by 180 degrees.
    from perception.shapes import make_object
    from tactile.sampling import explore_object

    model = make_object("mug", 0)
    seq = explore_object(model, "blind", 1, probes=9, seed=3)[0]
    frames, _ = FSRSensor().press(model, seq.positions[::-1], seq.normals[::-1], -seq.tangents[::-1])
    np.testing.assert_allclose(frames, seq.frames[::-1, ::-1, ::-1], atol=1e-4)


def test_reversal_of_the_invariant_cue_matches_the_cue_of_the_reversed_contour():
    batch = make_batch(n_per_class=2, probes=7)
    rng = np.random.default_rng(2)
    batch.positions = (batch.positions + rng.normal(size=batch.positions.shape)).astype(np.float32)
    batch.tangents = rng.normal(size=batch.tangents.shape).astype(np.float32)
    model = CNNClassifier(cue="invariant")
    cues = torch.from_numpy(kinesthetic_cues(batch, "invariant")).unsqueeze(1)
    gen = torch.Generator().manual_seed(0)
    out = model._augment(cues, "kinesthetic", gen)
    # the same draws, replayed: which sequences were shifted by how much and reversed
    gen = torch.Generator().manual_seed(0)
    shift = torch.randint(0, 7, (len(batch),), generator=gen).numpy()
    flip = (torch.rand(len(batch), generator=gen) < 0.5).numpy()
    assert flip.any() and not flip.all()
    for i in range(len(batch)):
        order = (np.arange(7) + shift[i]) % 7
        if flip[i]:
            order = order[::-1]
        moved = batch.subset([i])
        moved.positions, moved.normals = batch.positions[[i]][:, order], batch.normals[[i]][:, order]
        moved.tangents = batch.tangents[[i]][:, order] * (-1 if flip[i] else 1)
        moved.pad_sides_mm = batch.pad_sides_mm[[i]][:, order]
        moved.plane_normals = batch.plane_normals[[i]] * (-1 if flip[i] else 1)
        np.testing.assert_allclose(out[i, 0].numpy(), kinesthetic_cues(moved, "invariant")[0], atol=1e-4)


def _reread(batch: SequenceBatch, shift: int = 0, reverse: bool = False) -> SequenceBatch:
    """The same contours as if touched from probe ``shift`` on (and in the other direction): every per-probe
    array reordered, tangents and plane normal negated and frames turned by 180 degrees when reversed (what the
    sensor gives, test above)."""
    p = batch.n_probes
    order = (np.arange(p) + shift) % p
    if reverse:
        order = order[::-1]
    out = batch.subset(np.arange(len(batch)))
    out.frames = batch.frames[:, order][:, :, ::-1, ::-1].copy() if reverse else batch.frames[:, order].copy()
    out.positions, out.normals = batch.positions[:, order].copy(), batch.normals[:, order].copy()
    out.tangents = batch.tangents[:, order] * (-1 if reverse else 1)
    out.pad_sides_mm = batch.pad_sides_mm[:, order].copy()
    out.plane_normals = batch.plane_normals * (-1 if reverse else 1)
    return out


def test_test_views_average_the_sequence_read_from_other_starts_and_directions():
    train, test = make_batch(probes=6, seed=0), make_batch(n_per_class=3, probes=6, seed=1)
    rng = np.random.default_rng(3)
    test.positions = (test.positions + rng.normal(size=test.positions.shape)).astype(np.float32)
    model = CNNClassifier(cue="invariant", **{**FAST, "epochs": 3}).fit(train)
    plain = model.predict_proba_modalities(test)
    backwards = model.predict_proba_modalities(_reread(test, reverse=True))
    model.test_views = 2  # as touched, and reversed
    both = model.predict_proba_modalities(test)
    for modality in ("cutaneous", "kinesthetic"):  # each net's views averaged, then the nets combined
        np.testing.assert_allclose(both[modality], (plain[modality] + backwards[modality]) / 2, atol=1e-5)
    np.testing.assert_allclose(both["fusion"], fuse_modalities(both["cutaneous"], both["kinesthetic"]), atol=1e-9)
    model.test_views = 12  # every start of the 6 probes, both ways: the answer no longer depends on where or
    full = model.predict_proba(test)  # which way the touch went
    for shift, reverse in ((1, False), (4, True)):
        np.testing.assert_allclose(model.predict_proba(_reread(test, shift, reverse)), full, atol=1e-5)
    model.test_views = 1
    assert np.abs(model.predict_proba(_reread(test, 1)) - plain["fusion"]).max() > 1e-4  # the nets alone do


def test_modality_rules_by_hand():
    cutaneous, kinesthetic = np.array([[0.8, 0.2], [1.0, 0.0]]), np.array([[0.5, 0.5], [0.0, 1.0]])
    # product: sqrt(.8 * .5) : sqrt(.2 * .5) = 2 : 1; two nets that rule each other's class out: a tie
    np.testing.assert_allclose(fuse_modalities(cutaneous, kinesthetic), [[2 / 3, 1 / 3], [0.5, 0.5]], atol=1e-9)
    np.testing.assert_allclose(fuse_modalities(cutaneous, kinesthetic, "sum"), [[0.65, 0.35], [0.5, 0.5]])
    with pytest.raises(InvalidArgumentError, match="rule"):
        fuse_modalities(cutaneous, kinesthetic, "max")


def test_model_fuses_by_its_modality_rule_and_older_files_keep_the_sum(tmp_path):
    train = make_batch(n_per_class=6)
    model = CNNClassifier(**{**FAST, "epochs": 2}).fit(train)
    out = model.predict_proba_modalities(train)
    geometric = np.sqrt(out["cutaneous"] * out["kinesthetic"])
    np.testing.assert_allclose(out["fusion"], geometric / geometric.sum(1, keepdims=True), atol=1e-9)
    np.testing.assert_allclose(model.predict_proba(train), out["fusion"], atol=1e-9)
    # a file written before the rule was a parameter: it loads summing, as it predicted then
    from fusion.modelfile import read_model_file, write_model_file

    description, arrays = read_model_file(model.save(tmp_path / "new.vtm"))
    del description["params"]["dict"]["modality_rule"]  # the encoded dict of the constructor parameters
    old = load_model(write_model_file(tmp_path / "old.vtm", description, arrays))
    assert old.modality_rule == "sum"
    np.testing.assert_allclose(old.predict_proba(train), (out["cutaneous"] + out["kinesthetic"]) / 2, atol=1e-6)
    assert load_model(tmp_path / "new.vtm").modality_rule == "product"


# ---------------------------------------------------------------------------------------- training
def test_learns_a_separable_problem_and_generalises():
    train, test = make_batch(seed=0), make_batch(n_per_class=10, seed=1)
    model = CNNClassifier(**FAST).fit(train)
    assert list(model.classes_) == ["class0", "class1", "class2"]
    for modality in ("cutaneous", "kinesthetic", "fusion"):
        assert accuracy(model, test, modality) == 1.0, modality
    assert model.score(test) == 1.0


def test_each_modality_reads_its_own_input():
    # The class only in the normals: the kinesthetic net finds it, the cutaneous net cannot beat chance.
    train = make_batch(informative=("kinesthetic",), seed=0, n_per_class=20)
    test = make_batch(informative=("kinesthetic",), seed=1, n_per_class=30)
    model = CNNClassifier(**FAST).fit(train)
    assert accuracy(model, test, "kinesthetic") == 1.0
    assert accuracy(model, test, "cutaneous") < 0.6  # chance is 1/3 (90 test sequences)
    only = CNNClassifier(modality="cutaneous", **FAST).fit(train)
    assert only.kinesthetic_net_ is None and set(only.predict_proba_modalities(test)) == {"cutaneous", "fusion"}


def test_invariant_cue_and_augmentation_train():
    train, test = make_batch(seed=0), make_batch(n_per_class=6, seed=1)
    model = CNNClassifier(cue="invariant", augment=True, modality="cutaneous", **FAST).fit(train)
    assert model.score(test) == 1.0


def test_early_stopping_keeps_the_best_epoch():
    model = CNNClassifier(**{**FAST, "epochs": 30, "patience": 2, "val_fraction": 0.25}).fit(make_batch())
    for history in model.history_.values():
        assert history["epochs"] < 30 and history["best_epoch"] == history["epochs"] - 2
        assert history["val_accuracy"] == 1.0


def test_early_stopping_holds_out_whole_objects():
    """Classes with several objects give whole objects to validation (none of them also in training); a
    class with one object gives sequences of it, and keeps some for training."""
    y = np.repeat([0, 1, 2], 12)
    objects = np.concatenate([np.repeat([0, 1, 2, 3], 3), np.repeat([4, 5, 6, 7], 3), np.full(12, 8)])
    train, val = CNNClassifier(val_fraction=0.25, random_state=3)._split(y, objects)
    assert sorted(np.concatenate([train, val]).tolist()) == list(range(36))
    for c, first in ((0, 0), (1, 4)):
        held = set(objects[val][y[val] == c])
        assert len(held) == 1 and held.isdisjoint(objects[train]) and held <= set(range(first, first + 4))
    assert (y[val] == 2).sum() == 3 and (y[train] == 2).sum() == 9  # round(0.25 x 12) sequences of object 8


def test_seeded_fits_give_identical_predictions_and_leave_torch_settings_alone():
    train, test = make_batch(seed=0), make_batch(n_per_class=4, seed=1)
    threads, deterministic = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    rng_state = torch.random.get_rng_state()
    kw = {**FAST, "epochs": 3, "augment": True}
    a = CNNClassifier(random_state=5, **kw).fit(train).predict_proba_modalities(test)
    b = CNNClassifier(random_state=5, **kw).fit(train).predict_proba_modalities(test)
    c = CNNClassifier(random_state=6, **kw).fit(train).predict_proba_modalities(test)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["cutaneous"], c["cutaneous"])
    assert torch.get_num_threads() == threads and torch.are_deterministic_algorithms_enabled() == deterministic
    assert torch.equal(torch.random.get_rng_state(), rng_state)  # the caller's random stream is untouched
    assert torch.utils.deterministic.fill_uninitialized_memory is True  # torch's default, restored


def test_training_without_nan_fills_gives_the_same_weights(monkeypatch):
    """Training turns off deterministic mode's NaN fills of new tensors (for speed); with them on, the same seed
    must give the same weights to the bit, else some kernel read memory it had not written."""
    train = make_batch(seed=0)
    kw = {**FAST, "epochs": 2, "augment": True}
    seen = []
    original = cnn_module.CNNClassifier._train_net

    def recording(self, *args, **kwargs):
        seen.append(torch.utils.deterministic.fill_uninitialized_memory)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(cnn_module.CNNClassifier, "_train_net", recording)
    fast = CNNClassifier(random_state=2, **kw).fit(train)
    assert seen == [False, False]
    settings = cnn_module._torch_settings

    @contextlib.contextmanager
    def with_fills(threads, deterministic):
        with settings(threads, deterministic):
            torch.utils.deterministic.fill_uninitialized_memory = True
            yield

    monkeypatch.setattr(cnn_module, "_torch_settings", with_fills)
    filled = CNNClassifier(random_state=2, **kw).fit(train)
    assert seen[2:] == [True, True]
    for name in ("cutaneous_net_", "kinesthetic_net_"):
        for key, value in getattr(fast, name).state_dict().items():
            assert torch.equal(value, getattr(filled, name).state_dict()[key]), (name, key)


def test_statistics_come_from_the_training_frames():
    train = make_batch(seed=0)
    model = CNNClassifier(cue="normals", **{**FAST, "epochs": 1}).fit(train)
    assert model.frame_mean_ == pytest.approx(float(train.frames.astype(np.float64).mean()), rel=1e-6)
    np.testing.assert_allclose(model.cue_mean_, train.normals.reshape(-1, 3).mean(axis=0), atol=1e-6)


# ------------------------------------------------------------------------------------- persistence
def test_save_load_predicts_identically_and_refuses_another_sensor(tmp_path):
    train, test = make_batch(seed=0), make_batch(n_per_class=4, seed=1)
    model = CNNClassifier(**{**FAST, "epochs": 2}).fit(train)
    path = model.save(tmp_path / "cnn.vtm")
    loaded = load_model(path)
    assert next(loaded.cutaneous_net_.parameters()).device.type == "cpu"
    for key, value in model.predict_proba_modalities(test).items():
        np.testing.assert_array_equal(loaded.predict_proba_modalities(test)[key], value)
    other = make_batch(n_per_class=2, spec=FSRSensor(rows=8, cols=8, side_mm=15.0).spec())
    with pytest.raises(ModelMismatchError, match="side_mm"):
        loaded.predict(other)
    with pytest.raises(ModelMismatchError, match="probes"):
        loaded.predict(make_batch(n_per_class=2, probes=6))


def test_the_same_training_saves_the_same_bytes(tmp_path):
    """Two fits with the same seed save byte-identical files: the wall-clock seconds per epoch, which the saved
    history held, stay on the fitted model (``epoch_seconds_``) and are not written."""
    train = make_batch(seed=0)
    first, second = (CNNClassifier(**{**FAST, "epochs": 2}).fit(train) for _ in range(2))
    assert set(first.epoch_seconds_) == {"cutaneous", "kinesthetic"} and min(first.epoch_seconds_.values()) > 0
    a, b = first.save(tmp_path / "a.vtm"), second.save(tmp_path / "b.vtm")
    assert a.read_bytes() == b.read_bytes()
    assert not hasattr(load_model(a), "epoch_seconds_")


# ---------------------------------------------------------------------------------------- numerics
def test_constant_and_huge_inputs_give_finite_probabilities():
    train = make_batch(informative=("kinesthetic",))
    train.frames[:] = 0.0  # a constant video: no spread to divide by
    model = CNNClassifier(**{**FAST, "epochs": 2}).fit(train)
    assert model.frame_std_ == 1.0
    huge = make_batch(n_per_class=2)
    huge.frames[:] = 3e38
    for proba in model.predict_proba_modalities(huge).values():
        assert np.isfinite(proba).all() and np.allclose(proba.sum(1), 1.0)


@pytest.mark.parametrize("n_train,batch_size,steps", [(48, 16, 3), (49, 16, 3), (50, 16, 4), (1, 16, 1), (7, 64, 1)])
def test_steps_per_epoch_counts_the_batches_the_loop_runs(n_train, batch_size, steps):
    # 49 = 3 x 16 + 1: the last batch of one sequence is skipped (batch norm); 50 leaves a batch of two.
    assert CNNClassifier(batch_size=batch_size)._steps_per_epoch(n_train) == steps


@pytest.mark.parametrize("n_train,cutaneous,kinesthetic", [(18240, 18, 50), (4752, 67, 100), (3168, 100, 100),
                                                             (2112, 100, 100), (64, 100, 100)])
def test_default_recipe_epochs_by_training_set_size(n_train, cutaneous, kinesthetic):
    # Default: 100 epochs of batches of 64, at most 5,000 steps of the cutaneous net and 14,000 of the kinesthetic
    # one. The paper protocol's training part (18,240 sequences: 285 steps an epoch) stops after ceil(5000 / 285) =
    # 18 cutaneous epochs and ceil(14000 / 285) = 50 kinesthetic ones; new_instances' training set (99 objects x 48 =
    # 4,752: 74 batches + 16, 75 steps) after ceil(5000 / 75) = 67 cutaneous epochs (kinesthetic: all 100, 7,500
    # steps); an unseen-objects fold (66 x 48 = 3,168: 49 batches + 32, 50 steps) and smaller sets train all 100.
    model = CNNClassifier()
    assert model.max_steps == (5000, 14000)
    assert model.epochs_for(n_train, "cutaneous") == cutaneous
    assert model.epochs_for(n_train, "kinesthetic") == kinesthetic


@pytest.mark.parametrize("max_steps,cutaneous,kinesthetic", [(5000, 18, 18), (None, 100, 100), ((None, 300), 100, 2),
                                                               ((570, None), 2, 100), ([286, 285], 2, 1)])
def test_a_step_cap_is_one_for_both_nets_or_a_pair(max_steps, cutaneous, kinesthetic):
    # 18,240 sequences: 285 steps an epoch.
    model = CNNClassifier(max_steps=max_steps)
    assert (model.epochs_for(18240, "cutaneous"), model.epochs_for(18240, "kinesthetic")) == (cutaneous, kinesthetic)


@pytest.mark.parametrize("bad", [(5000,), (1, 2, 3), (0, 5000), (5000, -1), (5000, 2.5), (True, 5000), ("a", None), {}])
def test_a_step_cap_pair_of_anything_else_is_refused(bad):
    with pytest.raises(InvalidArgumentError, match="max_steps must be a positive integer"):
        CNNClassifier(max_steps=bad).epochs_for(100, "cutaneous")


def test_each_net_trains_under_its_own_cap(step_rates):
    # 30 sequences in batches of 16: 2 steps per epoch. Caps (3, 8): the cutaneous net runs ceil(3 / 2) = 2 epochs
    # (4 steps), the kinesthetic net ceil(8 / 2) = 4 (8 steps); each one-cycle schedule spans its own steps.
    model = CNNClassifier(**{**FAST, "epochs": 10, "lr": 2e-3, "max_steps": (3, 8)}).fit(make_batch(n_per_class=10))
    assert model.history_["cutaneous"]["epochs"] == 2 and model.history_["kinesthetic"]["epochs"] == 4
    assert len(step_rates) == 4 + 8
    assert step_rates[0] == step_rates[4] == pytest.approx(2e-3 / 25)  # each net's schedule starts anew
    assert step_rates[3] < 2e-3 / 100 and step_rates[-1] < 2e-3 / 100  # and ends at its own last step


def test_epoch_projection_takes_the_default_epochs_cut_at_the_step_cap():
    # The paper's 18,240 training sequences: 285 steps an epoch, so the caps allow ceil(5000 / 285) = 18 (cutaneous)
    # and ceil(14000 / 285) = 50 (kinesthetic) of the default 100 epochs; a net that ran fewer in the benchmark's fit
    # is projected with those.
    from benchmarks.classifiers import epoch_projection

    assert epoch_projection(16, None, 0, 1)["epochs"] == {"cutaneous": 18, "kinesthetic": 50}
    assert epoch_projection(16, {"cutaneous": 30, "kinesthetic": 12}, 0, 1)["epochs"] == {"cutaneous": 18,
                                                                                       "kinesthetic": 12}


@pytest.mark.parametrize(("n_per_class", "batches"), [(11, 2), (10, 2), (12, 3)])
def test_training_limit_times_one_pass_per_batch_of_an_epoch(monkeypatch, n_per_class, batches):
    """The benchmark's training limit is the forward + backward passes of one epoch's batches: 33 sequences in
    batches of 16 are 2 (the last one of 1 is skipped, as training skips it), 30 are 16 + 14, 36 are 16 + 16 + 4.
    A clock that moves 0.5 s per reading makes every pass 0.5 s, so the limit is 0.5 s x batches; frames of 12 x 12
    taxels pooled to 8 x 8 must reach the net in that shape, or its first layer refuses them."""
    import benchmarks.classifiers as bench

    batch = make_batch(n_per_class=n_per_class, grid=(12, 12), n_classes=3)
    model = CNNClassifier(**{**FAST, "epochs": 1, "frame_size": 8}).fit(batch)
    ticks = iter(np.arange(0.0, 1e6, 0.5))
    monkeypatch.setattr(bench.time, "perf_counter", lambda: float(next(ticks)))
    limits = bench.training_limit(model, batch, threads=1, steps=4)
    for kind in ("cutaneous", "kinesthetic"):
        assert limits[kind]["limit_epoch_s"] == pytest.approx(0.5 * batches)
        assert limits[kind]["ratio"] == pytest.approx(0.5 * batches / model.epoch_seconds_[kind])


@pytest.fixture
def step_rates(monkeypatch) -> list[float]:
    """The learning rate of every AdamW step taken while the test runs, in order."""
    seen = []
    original = torch.optim.AdamW.step

    def step(self, *args, **kwargs):
        seen.append(self.param_groups[0]["lr"])
        return original(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.AdamW, "step", step)
    return seen


def test_one_cycle_schedule_peaks_at_lr_and_runs_exactly_its_steps(step_rates):
    # The schedule must be stepped once per batch, reach lr at 30 % of the steps (OneCycleLR's default warm-up
    # share) and end near lr / (25 * 1e4).
    seen = step_rates
    batch = make_batch(n_per_class=10)  # 30 sequences: 16 + 14 per epoch, 2 steps
    CNNClassifier(**{**FAST, "epochs": 10, "lr": 2e-3, "modality": "kinesthetic"}).fit(batch)
    assert len(seen) == 20
    assert max(seen) == pytest.approx(2e-3, rel=0.02) and int(np.argmax(seen)) in (5, 6)
    assert seen[0] == pytest.approx(2e-3 / 25) and seen[-1] < 2e-3 / 100


@pytest.mark.parametrize("max_steps,epochs_run", [(None, 10), (7, 4), (8, 4), (9, 5), (500, 10), (1, 1)])
def test_max_steps_cuts_the_epochs_and_the_schedule_spans_those_that_run(step_rates, max_steps, epochs_run):
    # 30 sequences in batches of 16: 2 steps per epoch, so a cap of 7 steps needs ceil(7 / 2) = 4 epochs (8 steps);
    # the one-cycle schedule covers exactly the steps run: it starts at lr / 25 and ends far below the peak.
    seen = step_rates
    model = CNNClassifier(**{**FAST, "epochs": 10, "lr": 2e-3, "modality": "kinesthetic", "max_steps": max_steps})
    model.fit(make_batch(n_per_class=10))
    assert len(seen) == 2 * epochs_run and model.history_["kinesthetic"]["epochs"] == epochs_run
    if epochs_run > 1:  # (OneCycleLR over 2 steps has no warm-up to speak of)
        assert seen[0] == pytest.approx(2e-3 / 25)
        assert max(seen) == pytest.approx(2e-3, rel=0.3) and seen[-1] < 2e-3 / 100


@pytest.mark.parametrize("name", ["max_steps", "epochs", "batch_size"])
@pytest.mark.parametrize("bad", [0, -5, 2.5, "many", True, float("nan"), float("inf"), None, 2**64])
def test_counts_must_be_positive_integers(name, bad):
    if name == "max_steps" and bad is None:
        pytest.skip("max_steps=None means no cap")
    if bad == 2**64:  # a whole number, merely huge: allowed (checked, never allocated)
        assert CNNClassifier(**{**FAST, name: bad})._check_params() is None
        return
    with pytest.raises(InvalidArgumentError, match=f"{name} must be a positive integer"):
        CNNClassifier(**{**FAST, name: bad}).fit(make_batch(n_per_class=4))


def test_older_model_files_load_as_trained_without_a_step_cap(tmp_path):
    model = CNNClassifier(**{**FAST, "epochs": 1}).fit(make_batch(n_per_class=4))
    assert model.max_steps == (5000, 14000)  # the default caps
    from fusion.modelfile import read_model_file, write_model_file

    description, arrays = read_model_file(model.save(tmp_path / "new.vtm"))
    assert load_model(tmp_path / "new.vtm").max_steps == (5000, 14000)
    description["params"]["dict"]["max_steps"] = 5000  # a file written when one cap held for both nets
    assert load_model(write_model_file(tmp_path / "one.vtm", description, arrays)).max_steps == 5000
    del description["params"]["dict"]["max_steps"]  # a file written before the cap was a parameter
    assert load_model(write_model_file(tmp_path / "old.vtm", description, arrays)).max_steps is None


def test_paper_recipe_is_plain_adam_at_a_constant_rate(monkeypatch):
    made = []
    for cls in (torch.optim.Adam, torch.optim.AdamW):
        monkeypatch.setattr(cls, "step", lambda self, *a, _c=cls, _s=cls.step, **k: (made.append(_c.__name__), _s(self, *a, **k))[1])
    batch = make_batch(n_per_class=10)
    model = CNNClassifier(**{**FAST, "epochs": 2, "schedule": "constant", "weight_decay": 0.0, "label_smoothing": 0.0,
                             "modality": "kinesthetic"}).fit(batch)
    assert set(made) == {"Adam"} and len(made) == 4 and model.history_["kinesthetic"]["epochs"] == 2


def test_bad_input_is_refused():
    train = make_batch(n_per_class=3)
    nan = make_batch(n_per_class=3)
    nan.frames[0, 0, 0, 0] = np.nan
    with pytest.raises(DatasetError, match="NaN"):
        CNNClassifier(**FAST).fit(nan)
    with pytest.raises(DatasetError, match="one class"):
        CNNClassifier(**FAST).fit(train.subset(train.labels == 0))
    with pytest.raises(InvalidArgumentError, match="cue"):
        CNNClassifier(cue="colour", **FAST).fit(train)
    with pytest.raises(InvalidArgumentError, match="modality"):
        CNNClassifier(modality="smell", **FAST).fit(train)
    with pytest.raises(InvalidArgumentError, match="augment"):
        CNNClassifier(augment="sometimes", **FAST).fit(train)
    with pytest.raises(InvalidArgumentError, match="val_fraction"):
        CNNClassifier(**{**FAST, "val_fraction": 1.0}).fit(train)
    for name, value in (("schedule", "cyclic"), ("weight_decay", -0.1), ("weight_decay", np.nan),
                        ("label_smoothing", 1.0), ("label_smoothing", -0.2), ("test_views", 3), ("test_views", 0),
                        ("test_views", True), ("modality_rule", "max")):
        with pytest.raises(InvalidArgumentError, match=name):
            CNNClassifier(**{**FAST, name: value}).fit(train)
    model = CNNClassifier(**{**FAST, "epochs": 1}).fit(train)
    with pytest.raises(DatasetError, match="NaN"):
        model.predict(nan)
    model.test_views = 5  # set on a fitted model: refused at prediction
    with pytest.raises(InvalidArgumentError, match="test_views"):
        model.predict(train)
    model.test_views = 12  # more than every start both ways (5 probes): nothing new to average, refused
    with pytest.raises(InvalidArgumentError, match="at most 10"):
        model.predict(train)
    with pytest.raises(InvalidArgumentError, match="at most 10"):
        CNNClassifier(**{**FAST, "test_views": 12}).fit(train)


def test_a_model_file_asking_for_millions_of_views_is_refused(tmp_path):
    """A hostile file must not make prediction hang or exhaust memory: views are bounded by the probe count."""
    from fusion.modelfile import read_model_file, write_model_file
    from perception.errors import ModelFileError

    model = CNNClassifier(**{**FAST, "epochs": 1}).fit(make_batch(n_per_class=3))
    description, arrays = read_model_file(model.save(tmp_path / "m.vtm"))
    description["params"]["dict"]["test_views"] = 2_000_000
    with pytest.raises(ModelFileError, match="big.vtm.*test_views"):
        load_model(write_model_file(tmp_path / "big.vtm", description, arrays))


# ------------------------------------------------------------------------------------ catalogue data
@pytest.mark.slow
def test_recognizes_guided_catalogue_contours():
    # 10 catalogue classes x 2 objects x 20 guided contours, 80/20 by sequence (the paper's protocol, small).
    from benchmarks.classifiers import catalogue_batch, split

    batch = catalogue_batch(objects=2, contours=20, strategy="guided", seed=0)
    train, test = split(batch, "sequence", seed=0)
    model = CNNClassifier(epochs=40, progress=False).fit(batch.subset(train))
    assert accuracy(model, batch.subset(test)) >= 0.85


def test_label_smoothing_bounds_the_confidence_it_trains_towards():
    # Cross-entropy against smoothed targets is smallest at the target itself: with share s over C classes the
    # true class gets 1 - s + s / C (2/3 for s = 0.5, C = 3), so a net trained to convergence on a separable
    # problem stays near it, while without smoothing it goes to ~1.
    batch = make_batch(n_per_class=16, informative=("kinesthetic",))
    common = {**FAST, "epochs": 40, "modality": "kinesthetic", "schedule": "constant", "lr": 3e-3}
    sharp = CNNClassifier(**common, label_smoothing=0.0).fit(batch).predict_proba(batch).max(1).mean()
    smooth = CNNClassifier(**common, label_smoothing=0.5).fit(batch).predict_proba(batch).max(1).mean()
    assert sharp > 0.9 and abs(smooth - 2 / 3) < 0.08


def test_test_views_spread_their_starts_evenly_over_the_probes():
    """4 views of 6-probe contours: starts 0 and 3 (6 / 2 apart), each read both ways: the mean of the four
    re-read sequences predicted one view at a time."""
    train, test = make_batch(probes=6, seed=0), make_batch(n_per_class=3, probes=6, seed=1)
    model = CNNClassifier(cue="invariant", **{**FAST, "epochs": 3}).fit(train)
    reads = [model.predict_proba_modalities(_reread(test, shift, reverse))
             for shift in (0, 3) for reverse in (False, True)]
    model.test_views = 4
    out = model.predict_proba_modalities(test)
    for modality in ("cutaneous", "kinesthetic"):
        np.testing.assert_allclose(out[modality], np.mean([r[modality] for r in reads], axis=0), atol=1e-5)


def test_paper_cnn_sums_the_two_nets_and_the_pose_free_cnn_multiplies():
    """default_classifiers: "cnn-normals" (the paper's) fuses by the mean of the nets' probabilities, "cnn" by
    their normalised geometric mean."""
    from fusion.experiments.models import default_classifiers

    batch = make_batch(n_per_class=4)
    factories = default_classifiers(seed=0, epochs=1)
    for name, rule in (("cnn-normals", "sum"), ("cnn", "product")):
        model = factories[name]()
        model.set_params(threads=1)
        out = model.fit(batch).predict_proba_modalities(batch)
        c, k = out["cutaneous"], out["kinesthetic"]
        geometric = np.sqrt(c * k) / np.sqrt(c * k).sum(1, keepdims=True)
        np.testing.assert_allclose(out["fusion"], (c + k) / 2 if rule == "sum" else geometric, atol=1e-9,
                                   err_msg=name)
        assert not np.allclose((c + k) / 2, geometric, atol=1e-6)  # the two rules differ on these outputs


def test_paper_cnn_reads_8_by_8_frames_and_the_pose_free_cnn_16_by_16():
    """default_classifiers: the paper's pair pools 32 x 32 frames to 8 x 8 taxels (PAPER_FRAME_SIZE), the pose-free
    pair to 16 x 16: the cutaneous net's first fully connected layer reads the flattened 16 channels x 5 probes x
    (side / 4)^2 features of two stride-2 convolutions (hand-computed: 16 * 5 * 2 * 2 = 320 and 16 * 5 * 4 * 4 = 1,280)."""
    from fusion.experiments.models import default_classifiers

    batch = make_batch(n_per_class=4, grid=(32, 32))
    factories = default_classifiers(seed=0, epochs=1)
    for name, features in (("cnn-normals", 320), ("cnn", 1280)):
        model = factories[name]()
        model.set_params(threads=1)
        model.fit(batch)
        assert model.cutaneous_net_.fc1.in_features == features, name


# ------------------------------------------------------------------------------------------ embedding
def test_embed_gives_the_hidden_layer_each_net_classifies_with_unit_length():
    """``embed`` is, per net, the hidden layer that its last layer turns into the predicted probabilities: fc2 of
    the (unnormalised) hidden layer read by a hook on fc1 gives ``predict_proba_modalities``; each net's part has
    unit length and the two parts are weighted equally."""
    batch = make_batch()
    model = CNNClassifier(**FAST, random_state=2).fit(batch)
    hidden = {}

    def keep(kind):
        def hook(module, inputs, out):  # returns None: the forward pass goes on unchanged
            hidden[kind] = torch.relu(out).detach().double()
        return hook

    hooks = [getattr(model, f"{kind}_net_").fc1.register_forward_hook(keep(kind))
             for kind in ("cutaneous", "kinesthetic")]
    proba = model.predict_proba_modalities(batch)
    for hook in hooks:
        hook.remove()
    emb = model.embed(batch)
    assert emb.shape == (len(batch), 128) and emb.dtype == np.float64 and np.isfinite(emb).all()
    for j, kind in enumerate(("cutaneous", "kinesthetic")):
        h = hidden[kind].numpy()
        net = getattr(model, f"{kind}_net_")
        logits = h @ net.fc2.weight.detach().double().numpy().T + net.fc2.bias.detach().double().numpy()
        soft = np.exp(logits - logits.max(1, keepdims=True))
        np.testing.assert_allclose(soft / soft.sum(1, keepdims=True), proba[kind], atol=1e-5)
        part = emb[:, 64 * j:64 * (j + 1)]
        np.testing.assert_allclose(part * np.sqrt(2), h / np.linalg.norm(h, axis=1, keepdims=True), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-12)


def test_embed_of_one_modality_and_its_errors():
    batch = make_batch()
    model = CNNClassifier(**FAST, modality="kinesthetic").fit(batch)
    emb = model.embed(batch)
    assert emb.shape == (len(batch), 64)
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-12)
    other = make_batch(grid=(4, 4), spec=FSRSensor(rows=4, cols=4).spec())
    with pytest.raises(ModelMismatchError):
        model.embed(other)


@pytest.fixture(scope="module")
def fitted_pair():
    batch = make_batch()
    return CNNClassifier(**FAST, random_state=2).fit(batch), batch


def test_embed_reads_the_nets_in_eval_mode_and_in_any_chunks(fitted_pair, monkeypatch):
    """Left in training mode (dropout, batch statistics), the nets would give other features; chunks of 5 give
    the features of one pass."""
    import fusion.cnn

    model, batch = fitted_pair
    whole = model.embed(batch)
    model.cutaneous_net_.train()
    model.kinesthetic_net_.train()
    np.testing.assert_array_equal(model.embed(batch), whole)
    monkeypatch.setattr(fusion.cnn, "PREDICT_CHUNK", 5)
    np.testing.assert_allclose(model.embed(batch), whole, atol=1e-5)


def test_the_fusion_model_joined_from_its_two_nets_is_the_one_fit(fitted_pair, tmp_path):
    """Each net is seeded and trains on its own: a cutaneous-only and a kinesthetic-only model fitted apart join
    into the fusion model one fit gives, weight for weight (what lets the experiments train the nets side by
    side)."""
    model, batch = fitted_pair
    params = model.get_params()
    apart = {net: CNNClassifier(**{**params, "modality": net}).fit(batch) for net in ("cutaneous", "kinesthetic")}
    joined = CNNClassifier.from_nets(apart["cutaneous"], apart["kinesthetic"])
    assert joined.get_params() == params
    for net in ("cutaneous_net_", "kinesthetic_net_"):
        mine, theirs = getattr(joined, net).state_dict(), getattr(model, net).state_dict()
        assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine), net
    assert (joined.frame_mean_, joined.frame_std_) == (model.frame_mean_, model.frame_std_)
    np.testing.assert_array_equal(joined.cue_std_, model.cue_std_)
    assert joined.history_ == {net: apart[net].history_[net] for net in apart}
    test = make_batch(n_per_class=4, seed=1)
    expected = model.predict_proba_modalities(test)
    joined.save(tmp_path / "joined.vtm")
    again = load_model(tmp_path / "joined.vtm")
    for key, value in expected.items():
        np.testing.assert_array_equal(joined.predict_proba_modalities(test)[key], value, err_msg=key)
        np.testing.assert_array_equal(again.predict_proba_modalities(test)[key], value, err_msg=key)


def test_joining_nets_refuses_models_that_do_not_belong_together(fitted_pair):
    model, batch = fitted_pair
    params = model.get_params()

    def fit(net, data=batch, **changed):
        return CNNClassifier(**{**params, "modality": net, **changed}).fit(data)

    cutaneous, kinesthetic = fit("cutaneous"), fit("kinesthetic")
    with pytest.raises(InvalidArgumentError, match="the cutaneous argument must be a fitted"):
        CNNClassifier.from_nets(kinesthetic, cutaneous)  # swapped
    with pytest.raises(InvalidArgumentError, match="the cutaneous argument must be a fitted"):
        CNNClassifier.from_nets(model, kinesthetic)  # a fusion model
    with pytest.raises(InvalidArgumentError, match="the kinesthetic argument must be a fitted"):
        CNNClassifier.from_nets(cutaneous, CNNClassifier(**{**params, "modality": "kinesthetic"}))  # not fitted
    with pytest.raises(InvalidArgumentError, match="other parameters"):
        CNNClassifier.from_nets(cutaneous, fit("kinesthetic", random_state=9))
    with pytest.raises(InvalidArgumentError, match="fitted on other data"):
        CNNClassifier.from_nets(cutaneous, fit("kinesthetic", make_batch(seed=4)))
    for changed in ({"extra_": 1.0}, {"cue_std_": kinesthetic.cue_std_ * 2}):
        odd = copy.copy(kinesthetic)
        vars(odd).update(changed)
        with pytest.raises(InvalidArgumentError, match="fitted on other data"):
            CNNClassifier.from_nets(cutaneous, odd)
    for broken in ({"history_": {}}, {"kinesthetic_net_": cutaneous.cutaneous_net_}):
        odd = copy.copy(kinesthetic)
        vars(odd).update(broken)
        with pytest.raises(InvalidArgumentError, match="the kinesthetic argument must be a fitted"):
            CNNClassifier.from_nets(cutaneous, odd)


def test_nets_saved_apart_join_after_loading(fitted_pair, tmp_path):
    """Two nets trained apart (e.g. on two machines) and saved join as read back from their files."""
    model, batch = fitted_pair
    params = model.get_params()
    for net in ("cutaneous", "kinesthetic"):
        CNNClassifier(**{**params, "modality": net}).fit(batch).save(tmp_path / f"{net}.vtm")
    joined = CNNClassifier.from_nets(load_model(tmp_path / "cutaneous.vtm"), load_model(tmp_path / "kinesthetic.vtm"))
    test = make_batch(n_per_class=4, seed=1)
    np.testing.assert_array_equal(joined.predict_proba(test), model.predict_proba(test))


def test_predictions_are_the_same_bytes_on_any_thread_count(fitted_pair):
    """Training sums in an order that depends on the thread count (the experiments fix it), the forward pass does
    not: the noise part predicts on every core with models trained on one thread."""
    model, _ = fitted_pair
    batch = make_batch(n_per_class=200, seed=5)
    outputs = []
    for threads in (1, 2, 3):
        model.set_params(threads=threads)
        outputs.append(model.predict_proba_modalities(batch))
    model.set_params(threads=FAST["threads"])
    for other in outputs[1:]:
        for name in ("cutaneous", "kinesthetic", "fusion"):
            np.testing.assert_array_equal(other[name], outputs[0][name], err_msg=name)


def test_embed_of_a_silent_net_adds_zeros_not_nan():
    model = CNNClassifier(**FAST, random_state=2).fit(make_batch())
    with torch.no_grad():
        model.cutaneous_net_.fc1.bias.fill_(-1e6)  # every hidden ReLU off
    emb = model.embed(make_batch())
    assert np.isfinite(emb).all() and np.abs(emb[:, :64]).max() == 0
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), np.sqrt(0.5), atol=1e-12)


@pytest.mark.parametrize("params,n_train", [({}, 0), ({}, -5), ({}, 2.5), ({}, True), ({"batch_size": 0}, 10),
                                            ({"max_steps": 0}, 10)])
def test_epochs_for_refuses_what_it_cannot_count(params, n_train):
    with pytest.raises(InvalidArgumentError):
        CNNClassifier(**params).epochs_for(n_train, "cutaneous")


def test_epochs_for_names_the_nets_it_counts_for():
    with pytest.raises(InvalidArgumentError, match="net must be one of"):
        CNNClassifier().epochs_for(100, "fusion")


# ------------------------------------- step caps read from model files (from a break attempt)

@pytest.fixture(scope="module")
def saved_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("caps") / "m.vtm"
    CNNClassifier(**{**FAST, "epochs": 1}).fit(make_batch(n_per_class=4)).save(path)
    return read_model_file(path)


@pytest.mark.parametrize("caps", [[1, 2, 3], {"tuple": [1, 2, 3]}, {"dict": {"a": 1}}, "x", [0, 5], [True, 5],
                                  [5, 2.5], [], {"float": "nan"}])
def test_a_model_file_with_bad_step_caps_is_refused_on_loading(saved_model, tmp_path, caps):
    description, arrays = saved_model
    description = {**description, "params": {"dict": {**description["params"]["dict"], "max_steps": caps}}}
    path = write_model_file(tmp_path / "bad.vtm", description, arrays)
    with pytest.raises(ModelFileError, match="max_steps must be a positive integer"):
        load_model(path)


@pytest.mark.parametrize("caps,expected", [([300, None], [300, None]), ({"tuple": [300, 400]}, (300, 400)),
                                           (None, None), (7, 7)])
def test_a_model_file_with_good_step_caps_loads_them(saved_model, tmp_path, caps, expected):
    description, arrays = saved_model
    description = {**description, "params": {"dict": {**description["params"]["dict"], "max_steps": caps}}}
    model = load_model(write_model_file(tmp_path / "ok.vtm", description, arrays))
    assert model.max_steps == expected
