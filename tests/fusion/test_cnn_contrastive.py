"""The supervised contrastive term (``CNNClassifier(contrastive_weight=...)``): the loss against hand-computed values,
its edge cases, and what it does to a fitted model's feature space."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fusion import cnn
from fusion.base import load_model
from fusion.cnn import CONTRASTIVE_TEMPERATURE, MAX_CONTRASTIVE_WEIGHT, CNNClassifier, supervised_contrastive
from fusion.experiments.touch import touch_objects
from perception.errors import InvalidArgumentError
from perception.shapes import make_object
from tactile import FSRSensor
from tests.fusion.test_cnn_outliers import outlier_store  # noqa: F401 -- fixture

T = CONTRASTIVE_TEMPERATURE


def test_two_alike_rows_and_an_outlier_at_right_angles():
    """Anchors 0 and 1 (one class) point the same way, the outlier at 90 degrees: each anchor's share of its positive
    is e^(1/t) / (e^(1/t) + e^0), so the loss is log(1 + e^(-1/t))."""
    hidden = torch.tensor([[2.0, 0.0], [0.5, 0.0], [0.0, 3.0]], dtype=torch.float64)
    loss = supervised_contrastive(hidden, torch.tensor([0, 0]))
    assert float(loss.detach()) == pytest.approx(math.log1p(math.exp(-1 / T)), rel=1e-12)


def test_three_labelled_rows_at_sixty_and_ninety_degrees():
    """u0 = (1, 0), u1 at 60 degrees (class 0), u2 = (0, 1) (class 1, no positive: not an anchor). Anchor 0:
    log-share c/t - log(e^(c/t) + e^0); anchor 1: c/t - log(e^(c/t) + e^(s/t)); c = cos 60, s = sin 60."""
    c, s = math.cos(math.pi / 3), math.sin(math.pi / 3)
    hidden = torch.tensor([[1.0, 0.0], [c * 4, s * 4], [0.0, 0.1]], dtype=torch.float64)
    share0 = c / T - math.log(math.exp(c / T) + 1.0)
    share1 = c / T - math.log(math.exp(c / T) + math.exp(s / T))
    loss = supervised_contrastive(hidden, torch.tensor([0, 0, 1]))
    assert float(loss.detach()) == pytest.approx(-(share0 + share1) / 2, rel=1e-12)


@pytest.mark.parametrize("dtype, rel", [(torch.float32, 1e-5), (torch.float16, 2e-2), (torch.bfloat16, 3e-2)])
def test_lower_precision_gives_the_hand_computed_loss(dtype, rel):
    """The rows at 60 and 90 degrees above in float32 and half precision (whose range ends at -65504: the fill that
    hides a row from itself must fit the type): the hand-computed loss to the type's precision, finite gradients."""
    c, s = math.cos(math.pi / 3), math.sin(math.pi / 3)
    hidden = torch.tensor([[1.0, 0.0], [c * 4, s * 4], [0.0, 0.1]], dtype=dtype, requires_grad=True)
    share0 = c / T - math.log(math.exp(c / T) + 1.0)
    share1 = c / T - math.log(math.exp(c / T) + math.exp(s / T))
    loss = supervised_contrastive(hidden, torch.tensor([0, 0, 1]))
    loss.backward()
    assert loss.dtype == dtype
    assert float(loss.detach()) == pytest.approx(-(share0 + share1) / 2, rel=rel)
    assert torch.isfinite(hidden.grad).all()


@pytest.mark.parametrize("temperature", [0, 0.0, -0.1, float("nan"), float("inf"), True, "0.1", None, 10**400,
                                         -10**400, torch.tensor(0.1)])
def test_a_bad_temperature_is_refused(temperature):
    hidden = torch.tensor([[1.0, 0.0], [1.0, 0.1]], dtype=torch.float64)
    with pytest.raises(InvalidArgumentError, match="temperature must be a finite number > 0"):
        supervised_contrastive(hidden, torch.tensor([0, 0]), temperature=temperature)


def test_the_self_entry_stays_hidden_at_any_scale():
    """Rows u0 = (1, 0), u1 = u2 = (-1, 0), anchors 0 and 1 of one class, row 2 an outlier. Anchor 0's positive is
    opposite it and the outlier too, so its share is 1/2; anchor 1's positive is opposite and the outlier alike, so
    its log-share is -1/t - log(e^(-1/t) + e^(1/t)) = -2/t - log(1 + e^(-2/t)). The loss is
    (log 2 + 2/t + log(1 + e^(-2/t))) / 2 at any temperature: a finite fill (-1e9 before) stops hiding a row from
    itself once 1/t passes it."""
    hidden = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [-1.0, 0.0]], dtype=torch.float64)
    for t in (0.1, 1e-3, 1e-10):
        expected = (math.log(2) + 2 / t + math.log1p(math.exp(-2 / t))) / 2
        assert float(supervised_contrastive(hidden, torch.tensor([0, 0]), temperature=t)) == pytest.approx(
            expected, rel=1e-12)


def test_the_fill_leaves_room_below_the_log_sum_in_half_precision():
    """Three alike rows in float16 at t = 0.05: each anchor's share of its one positive is 1/2, loss log 2. A fill at
    the type's lowest value would overflow to -inf in the subtraction and make NaN."""
    hidden = torch.ones(3, 2, dtype=torch.float16, requires_grad=True)
    loss = supervised_contrastive(hidden, torch.tensor([0, 0, 1]), temperature=0.05)
    loss.backward()
    assert float(loss.detach()) == pytest.approx(math.log(2), rel=2e-2)
    assert torch.isfinite(hidden.grad).all()


@pytest.mark.parametrize("dtype, temperature", [(torch.float32, 1e-300), (torch.float16, 1e-6),
                                                (torch.float64, 5e-324)])
def test_a_temperature_too_small_for_the_type_is_refused(dtype, temperature):
    hidden = torch.tensor([[1.0, 0.0], [1.0, 0.1], [0.0, 1.0]], dtype=dtype)
    with pytest.raises(InvalidArgumentError, match="too small for"):
        supervised_contrastive(hidden, torch.tensor([0, 0, 1]), temperature=temperature)


@pytest.mark.parametrize("hidden", [torch.tensor([[1, 0], [1, 0]]), torch.tensor([[True, False], [True, True]]),
                                    torch.ones(2, 2, dtype=torch.complex64), [[1.0, 0.0], [1.0, 0.0]]])
def test_features_that_are_not_a_floating_tensor_are_refused(hidden):
    with pytest.raises(InvalidArgumentError, match="expected floating"):
        supervised_contrastive(hidden, torch.tensor([0, 0]))


@pytest.mark.parametrize("labels", [torch.tensor([[0], [0]]), torch.tensor(0), [0, 0], np.array([0, 0])])
def test_labels_that_are_not_a_1d_tensor_are_refused(labels):
    with pytest.raises(InvalidArgumentError, match="labels must be a 1-D tensor"):
        supervised_contrastive(torch.ones(2, 2, dtype=torch.float64), labels)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_features_holding_nan_or_inf_are_refused(bad):
    """One diverged row would make the whole loss NaN: the term says so instead of training on."""
    hidden = torch.tensor([[1.0, 0.0], [1.0, 0.1], [0.0, 1.0]], dtype=torch.float64)
    hidden[2, 1] = bad
    with pytest.raises(InvalidArgumentError, match="NaN or Inf"):
        supervised_contrastive(hidden, torch.tensor([0, 0]))


@pytest.mark.parametrize("shape", [(1, 2), (2,), (2, 2, 1)])
def test_features_of_the_wrong_shape_are_refused(shape):
    with pytest.raises(InvalidArgumentError, match=r"expected floating \(B, H\) features with B >= 2"):
        supervised_contrastive(torch.ones(shape, dtype=torch.float64), torch.tensor([0, 0]))


def test_no_anchor_with_a_positive_gives_zero_and_a_gradient_of_zeros():
    hidden = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=torch.float64, requires_grad=True)
    loss = supervised_contrastive(hidden, torch.tensor([0, 1, 2]))
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.equal(hidden.grad, torch.zeros_like(hidden))


def test_a_row_of_zeros_keeps_the_loss_and_gradient_finite():
    """A hidden layer whose ReLUs are all off has no direction: it must not produce NaN (0 / 0 in the scaling)."""
    hidden = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    loss = supervised_contrastive(hidden, torch.tensor([0, 0, 0]))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(hidden.grad).all()


def test_the_loss_reads_directions_only():
    rng = np.random.default_rng(0)
    hidden = torch.from_numpy(rng.normal(size=(6, 4)))
    labels = torch.tensor([0, 0, 1, 1, 2])  # the sixth row is an outlier
    scale = torch.from_numpy(rng.uniform(0.1, 10, size=(6, 1)))
    assert float(supervised_contrastive(hidden * scale, labels)) == pytest.approx(
        float(supervised_contrastive(hidden, labels)), rel=1e-12)


SENSOR = FSRSensor(rows=8, cols=8)


@pytest.fixture(scope="module")
def known():
    """Touches of three classes (box, can, bowl), two objects each."""
    names = ["box", "can", "bowl"]
    objects = [make_object(n, s) for n in names for s in range(2)]
    return touch_objects(objects, [n for n in names for _ in range(2)], "blind", 12, sensor=SENSOR, probes=10)


def model(**params) -> CNNClassifier:
    return CNNClassifier(**{"epochs": 40, "progress": False, "threads": 1, **params})


def _spread(model, batch) -> float:
    """Mean distance of a sequence's unit feature vector to its class's mean vector, over the mean distance between
    class means (smaller: classes more compact relative to their separation)."""
    emb = model.embed(batch)
    labels = np.asarray(batch.labels)
    means = np.stack([emb[labels == c].mean(axis=0) for c in np.unique(labels)])
    within = np.mean([np.linalg.norm(emb[labels == c] - means[i], axis=1).mean()
                      for i, c in enumerate(np.unique(labels))])
    between = np.mean([np.linalg.norm(a - b) for i, a in enumerate(means) for b in means[i + 1:]])
    return within / between


def test_the_term_gathers_each_class_in_the_feature_space(known):
    """Trained with the term, each class lies closer around its mean relative to the distance between the means
    (0.27 against 0.36 when written; a term that does nothing gives the plain model's value exactly)."""
    plain = model().fit(known)
    gathered = model(contrastive_weight=2.0).fit(known)
    assert _spread(gathered, known) < _spread(plain, known), (_spread(gathered, known), _spread(plain, known))
    truth = np.asarray(known.class_names, dtype=object)[known.labels]
    assert np.mean(gathered.predict(known) == truth) >= 0.95


def test_a_zero_weight_is_the_plain_model_bit_for_bit(known):
    plain = model(epochs=3).fit(known)
    off = model(epochs=3, contrastive_weight=0.0).fit(known)
    for net in ("cutaneous_net_", "kinesthetic_net_"):
        a, b = getattr(plain, net).state_dict(), getattr(off, net).state_dict()
        assert all(np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)


def test_the_weight_survives_a_model_file(known, tmp_path):
    fitted = model(epochs=3, contrastive_weight=1.5).fit(known)
    fitted.save(tmp_path / "m.vtm")
    loaded = load_model(tmp_path / "m.vtm")
    assert loaded.contrastive_weight == 1.5
    assert np.array_equal(loaded.predict_proba(known), fitted.predict_proba(known))


@pytest.mark.parametrize("weight", [-0.1, float("nan"), float("inf"), MAX_CONTRASTIVE_WEIGHT * 2, True, "1", None])
def test_a_bad_weight_is_refused(known, weight):
    with pytest.raises(InvalidArgumentError, match="contrastive_weight"):
        model(contrastive_weight=weight).fit(known)


def test_outliers_are_negatives_only_even_when_two_point_alike():
    """Two outliers along (0, 1): they enlarge the anchors' denominators but are no anchors themselves (as anchors,
    each would be the other's positive and change the mean)."""
    c, s = math.cos(math.pi / 3), math.sin(math.pi / 3)
    hidden = torch.tensor([[1.0, 0.0], [c, s], [0.0, 1.0], [0.0, 2.0]], dtype=torch.float64)
    share0 = c / T - math.log(math.exp(c / T) + 2.0)
    share1 = c / T - math.log(math.exp(c / T) + 2 * math.exp(s / T))
    loss = supervised_contrastive(hidden, torch.tensor([0, 0]))
    assert float(loss.detach()) == pytest.approx(-(share0 + share1) / 2, rel=1e-12)


def test_the_temperature_is_the_one_given():
    hidden = torch.tensor([[2.0, 0.0], [0.5, 0.0], [0.0, 3.0]], dtype=torch.float64)
    loss = supervised_contrastive(hidden, torch.tensor([0, 0]), temperature=0.5)
    assert float(loss.detach()) == pytest.approx(math.log1p(math.exp(-2.0)), rel=1e-12)


def test_the_weight_scales_the_term(known):
    a = model(epochs=2, contrastive_weight=1.0).fit(known).cutaneous_net_.state_dict()
    b = model(epochs=2, contrastive_weight=2.0).fit(known).cutaneous_net_.state_dict()
    assert not all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("weight", [MAX_CONTRASTIVE_WEIGHT, np.float32(0.5), -0.0, 0])
def test_edge_weights_are_accepted(known, weight):
    model(epochs=1, contrastive_weight=weight).fit(known)


def test_a_huge_weight_is_refused_in_a_short_message(known):
    """10**5000 has more digits than Python will print: the message shows an abbreviation instead of failing."""
    with pytest.raises(InvalidArgumentError, match="contrastive_weight") as caught:
        model(contrastive_weight=10**5000).fit(known)
    assert len(str(caught.value)) < 200


def test_a_zero_weight_never_computes_the_term(known, monkeypatch):
    monkeypatch.setattr(cnn, "supervised_contrastive", lambda *a, **k: pytest.fail("computed at weight 0"))
    model(epochs=1).fit(known)


def test_the_term_reads_the_hidden_layer_with_the_outliers_rows(known, outlier_store, monkeypatch):  # noqa: F811
    seen, real = [], cnn.supervised_contrastive
    monkeypatch.setattr(cnn, "supervised_contrastive",
                        lambda h, y, *a, **k: seen.append((h.shape, len(y), h.requires_grad)) or real(h, y, *a, **k))
    model(epochs=1, outliers=outlier_store, contrastive_weight=1.0).fit(known)
    assert seen and all(shape == (2 * n, 64) and grad for shape, n, grad in seen)


def test_the_training_step_applies_dropout_as_forward_does(known, monkeypatch):
    modes, real = [], torch.nn.Dropout.forward
    monkeypatch.setattr(torch.nn.Dropout, "forward", lambda self, x: modes.append(self.training) or real(self, x))
    model(epochs=1).fit(known)
    assert any(modes)
