"""Model files: safetensors + JSON round trips, payloads never run, damaged / truncated / hostile files refused."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import save

from fusion.base import load_model
from fusion.cli import main
from fusion.cnn import CNNClassifier
from fusion.conventional import ConventionalClassifier
from fusion.experiments.models import Predictions, fit_cached
from fusion.modelfile import FORMAT_NAME
from perception.errors import ModelFileError
from tests._model_files import rewrite as rewrite_file
from tests.fusion._synthetic import circle_batch
from tests.fusion.test_base import MeanFrame
from tests.fusion.test_features import small_batch

FAST_CONVENTIONAL = {"som_iterations": 300, "n_select": 30, "search": None}
FAST_CNN = {"epochs": 2, "batch_size": 16, "progress": False, "threads": 1}


class Centroid(MeanFrame):
    """The nearest-mean stand-in, with extra fitted state of plain data (tuples, NaN, numpy scalars)."""

    def _fit(self, batch, y):
        super()._fit(batch, y)
        self.notes_ = {"fitted_on": len(y), "shape": (1, 2), "nan": float("nan"), "scale": np.float32(0.5)}


class Payload:
    """Unpickling this creates ``marker`` (builtins.open in mode "w"): proof that a load ran code."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


@pytest.fixture(scope="module")
def circles():
    return circle_batch([19, 20, 21, 22, 58, 60, 61, 63], labels=[0, 0, 0, 0, 1, 1, 1, 1])


@pytest.fixture(scope="module")
def models():
    """Fitted SVM, kNN and CNN on the small catalogue batch, shared (fitting costs seconds)."""
    batch = small_batch()
    fitted = {kind: ConventionalClassifier(kind=kind, **FAST_CONVENTIONAL).fit(batch) for kind in ("svm", "knn")}
    fitted["pca-knn"] = ConventionalClassifier(kind="knn", reduce="pca", **FAST_CONVENTIONAL).fit(batch)
    fitted["cnn"] = CNNClassifier(**FAST_CNN).fit(batch)
    fitted["cnn-kinesthetic"] = CNNClassifier(modality="kinesthetic", cue="invariant", **FAST_CNN).fit(batch)
    return fitted, batch


def rewrite(path, edit) -> None:
    """Apply ``edit(description, arrays)`` to a model file in place, resealed: a hostile file that passes every
    integrity check."""
    rewrite_file(path, path, edit)


# --------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("name", ["svm", "knn", "pca-knn", "cnn", "cnn-kinesthetic"])
def test_saved_and_loaded_models_predict_the_same_bytes(models, name, tmp_path):
    fitted, batch = models
    model = fitted[name]
    model.training_ = {"store": "x.zarr", "seed": 3}
    path = model.save(tmp_path / f"{name}.vtm")
    loaded = load_model(path)
    assert type(loaded) is type(model) and loaded.get_params() == model.get_params()
    assert loaded.predict_proba(batch).tobytes() == model.predict_proba(batch).tobytes()
    assert list(loaded.classes_) == list(model.classes_) and loaded.training_ == {"store": "x.zarr", "seed": 3}
    assert loaded.sensor_spec_ == model.sensor_spec_ and loaded.probes == model.probes
    # Same model, same bytes: saving again (or saving the loaded copy) writes an identical file.
    assert model.save(tmp_path / "again.vtm").read_bytes() == path.read_bytes()
    assert loaded.save(tmp_path / "copy.vtm").read_bytes() == path.read_bytes()


def test_plain_data_state_round_trips_with_its_types(circles, tmp_path):
    model = Centroid(temperature=2.0).fit(circles)
    loaded = load_model(model.save(tmp_path / "c.vtm"))
    assert loaded.temperature == 2.0 and loaded.centres_.tobytes() == model.centres_.tobytes()
    notes = loaded.notes_
    assert notes["fitted_on"] == 8 and notes["shape"] == (1, 2) and np.isnan(notes["nan"])
    assert type(notes["scale"]) is np.float32 and notes["scale"] == 0.5


def test_big_endian_state_is_saved_as_little_endian_and_loads(circles, tmp_path):
    # Fitted state in big-endian arrays (data read from a big-endian file) used to be written with a checksum of the
    # big-endian bytes while the file holds little-endian ones: its own loader refused it as damaged.
    model = Centroid().fit(circles)
    little = model.centres_.copy()
    model.centres_ = little.astype(little.dtype.newbyteorder(">"))
    model.notes_["counts"] = np.array([3, -2, 70000], dtype=">i4")
    model.notes_["scale"] = np.array(0.25, dtype=">f4")[()]  # a big-endian numpy scalar
    path = model.save(tmp_path / "big.vtm")
    loaded = load_model(path)
    assert loaded.centres_.dtype == little.dtype.newbyteorder("<") and loaded.centres_.tobytes() == little.tobytes()
    assert loaded.notes_["counts"].dtype == np.dtype("<i4") and loaded.notes_["counts"].tolist() == [3, -2, 70000]
    assert loaded.notes_["scale"] == 0.25 and loaded.notes_["scale"].dtype == np.float32
    assert loaded.predict_proba(circles).tobytes() == model.predict_proba(circles).tobytes()
    # The same model in native byte order writes the same file.
    model.centres_ = little
    model.notes_["counts"] = np.array([3, -2, 70000], dtype="<i4")
    model.notes_["scale"] = np.float32(0.25)
    assert model.save(tmp_path / "little.vtm").read_bytes() == path.read_bytes()


def test_model_files_are_safetensors_with_a_json_description(models, tmp_path):
    fitted, _ = models
    path = fitted["cnn"].save(tmp_path / "cnn.vtm")
    with safe_open(str(path), framework="numpy") as f:
        digest, _, text = f.metadata()["visuotactile-model"].partition(" ")
        description = json.loads(text)
        assert "cutaneous.fc1.weight" in set(f.keys()) and len(digest) == 64
    assert description["class"] == "fusion.cnn.CNNClassifier"
    assert description["classes"] == list(fitted["cnn"].classes_) and description["probes"] == 25
    assert description["grid"] == [16, 16] and description["cue"] == fitted["cnn"].cue
    assert {"numpy", "torch", "scikit-learn"} <= set(description["versions"])


# ------------------------------------------------------------------------------------------ payloads
def _payload_files(tmp_path, marker, circles) -> dict:
    """Every kind of file a user could hand to a loader, each carrying a payload that creates ``marker``."""
    files = {}
    pickled = pickle.dumps({"header": {"format": 1}, "model": Payload(marker)}, protocol=pickle.HIGHEST_PROTOCOL)
    for name in ("payload.vtm", "payload.pkl"):
        (tmp_path / name).write_bytes(pickled)
        files[name] = tmp_path / name
    for protocol in (2, 3, 4):
        path = tmp_path / f"protocol{protocol}.vtm"
        path.write_bytes(pickle.dumps(Payload(marker), protocol=protocol))
        files[path.name] = path
    torch.save({"model": Payload(marker)}, tmp_path / "torch.vtm")  # a zip holding data.pkl
    files["torch.vtm"] = tmp_path / "torch.vtm"
    # A safetensors file whose description is the pickle (as text).
    meta = {FORMAT_NAME: "0" * 64 + " " + pickled.decode("latin-1")}
    (tmp_path / "pickle-in-header.vtm").write_bytes(save({}, metadata=meta))
    files["pickle-in-header.vtm"] = tmp_path / "pickle-in-header.vtm"
    # A valid model file carrying the pickle's bytes as a tensor, referenced as a fitted attribute.
    good = Centroid().fit(circles).save(tmp_path / "pickle-as-tensor.vtm")

    def plant(description, arrays):
        arrays["payload"] = np.frombuffer(pickled, dtype=np.uint8).copy()
        description["state"]["fitted"]["dict"]["payload_"] = {"array": {"key": "payload", "order": "C"}}

    rewrite(good, plant)
    files["pickle-as-tensor.vtm"] = good
    return files


def test_no_loadable_file_kind_runs_a_planted_payload(circles, tmp_path, capsys):
    marker = tmp_path / "PAYLOAD_RAN"
    files = _payload_files(tmp_path, marker, circles)
    for name, path in files.items():
        if name == "pickle-as-tensor.vtm":
            loaded = load_model(path)  # data, never unpickled: the bytes come back as bytes
            assert loaded.payload_.dtype == np.uint8 and loaded.payload_.tobytes()[:1] == b"\x80"
        else:
            with pytest.raises(ModelFileError, match=name):
                load_model(path)
        assert not marker.exists(), name
    # Old pickles are refused with a message naming the opt-in.
    with pytest.raises(ModelFileError, match=r"pickle .*refused.*trust_pickle=True.*--trust-pickle"):
        load_model(files["payload.pkl"])
    # The command line: one line on stderr, exit 2, nothing run.
    store = tmp_path / "none.zarr"
    for name, path in files.items():
        if name == "pickle-as-tensor.vtm":
            continue
        assert main(["evaluate", "--model", str(path), "--store", str(store)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0], err
        assert main(["recognize", str(tmp_path / "any.off"), "--model", str(path)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0], err
    assert not marker.exists()
    # A report folder's caches: a pickle where a cached model or prediction is expected is not unpickled.
    path = tmp_path / "report" / "m.vtm"
    path.parent.mkdir()
    path.write_bytes(files["payload.vtm"].read_bytes())
    record = {"data": "a"}
    fit_cached(lambda: Centroid(), circles, path, record)  # writes its record, trains, overwrites the file
    path.write_bytes(files["payload.vtm"].read_bytes())  # now a matching record sits next to a pickle
    model, _ = fit_cached(lambda: Centroid(), circles, path, record)
    assert isinstance(model, Centroid) and not marker.exists()
    assert load_model(path).centres_.tobytes() == model.centres_.tobytes()  # trained again, saved safely
    npz = tmp_path / "report" / "pred.npz"
    np.savez(npz, meta=np.array([Payload(marker)], dtype=object), proba=np.zeros((1, 2)))
    assert Predictions.load(npz, record) is None and not marker.exists()
    # The opt-in does what it says: it unpickles (here, proof that the payloads above were live).
    with pytest.raises(ModelFileError, match="not a visuotactile model"):
        load_model(files["payload.vtm"], trust_pickle=True)
    assert marker.exists()


def test_trust_pickle_loads_an_old_model_made_by_its_user(circles, tmp_path):
    model = Centroid().fit(circles)
    old = tmp_path / "old.pkl"
    old.write_bytes(pickle.dumps({"header": {"format": 1}, "model": model}, protocol=pickle.HIGHEST_PROTOCOL))
    with pytest.raises(ModelFileError, match="trust_pickle"):
        load_model(old)
    loaded = load_model(old, trust_pickle=True)
    converted = load_model(loaded.save(tmp_path / "new.vtm"))  # saved again: the safe format
    assert converted.predict_proba(circles).tobytes() == model.predict_proba(circles).tobytes()


# ------------------------------------------------------------------------------------ damaged files
def test_every_truncation_and_every_flipped_byte_is_refused(circles, tmp_path):
    path = Centroid().fit(circles).save(tmp_path / "c.vtm")
    data = path.read_bytes()
    bad = tmp_path / "bad.vtm"
    for cut in range(len(data)):
        bad.write_bytes(data[:cut])
        with pytest.raises(ModelFileError, match="bad.vtm"):
            load_model(bad)
    for i in range(len(data)):
        flipped = bytearray(data)
        flipped[i] ^= 0x10
        bad.write_bytes(bytes(flipped))
        with pytest.raises(ModelFileError, match="bad.vtm"):
            load_model(bad)


@pytest.mark.parametrize("name", ["svm", "knn", "cnn"])
def test_truncated_and_damaged_large_models_are_refused(models, name, tmp_path):
    path = models[0][name].save(tmp_path / "m.vtm")
    data = path.read_bytes()
    rng = np.random.default_rng(0)
    for cut in [0, 7, 8, 9, 100, *rng.integers(0, len(data), 20), len(data) - 1]:
        path.write_bytes(data[:cut])
        with pytest.raises(ModelFileError, match="m.vtm"):
            load_model(path)
    for i in rng.integers(0, len(data), 30):
        flipped = bytearray(data)
        flipped[i] ^= 0x01
        path.write_bytes(bytes(flipped))
        with pytest.raises(ModelFileError, match="m.vtm"):
            load_model(path)


def test_size_limit_is_checked_before_reading(circles, tmp_path):
    path = Centroid().fit(circles).save(tmp_path / "c.vtm")
    with pytest.raises(ModelFileError, match="more than the 100-byte limit.*max_bytes"):
        load_model(path, max_bytes=100)
    assert isinstance(load_model(path, max_bytes=path.stat().st_size), Centroid)


def _set(keys, value):
    def edit(description, arrays):
        node = description
        for key in keys[:-1]:
            node = node[key]
        node[keys[-1]] = value
    return edit


HOSTILE_DESCRIPTIONS = {
    "newer format": (_set(["version"], 99), "newer than this library"),
    "no version": (_set(["version"], "2"), "no format version"),
    "unknown class": (_set(["class"], "os.system"), "not defined in this process"),
    "class is a list": (_set(["class"], ["x"]), "names no classifier class"),
    "classes not a list": (_set(["classes"], "ab"), "lacks a valid 'classes'"),
    "one class": (_set(["classes"], ["a"]), "2 to"),
    "repeated classes": (_set(["classes"], ["a", "a"]), "distinct"),
    "huge probe count": (_set(["probes"], 10**12), "probes in the model"),
    "probes as text": (_set(["probes"], "25"), "lacks a valid 'probes'"),
    "bad grid": (_set(["grid"], [4, -1]), "bad taxel grid"),
    "grid differs from sensor": (_set(["grid"], [8, 4]), "differs from its sensor"),
    "sensor spec junk": (_set(["sensor_spec"], {"dict": {"rows": "x"}}), "sensor specification is invalid"),
    "sensor spec missing": (_set(["sensor_spec"], None), "lacks a sensor specification"),
    "unknown parameter": (_set(["params", "dict", "evil"], 1), "has no parameters"),
    "params not a mapping": (_set(["params"], [1]), "lacks a valid 'params'"),
    "dunder attribute": (_set(["state", "fitted", "dict", "__class__"], "x"), "no fitted attribute '__class__'"),
    "parameter as attribute": (_set(["state", "fitted", "dict", "temperature"], 5), "no fitted attribute"),
    "missing array": (_set(["state", "fitted", "dict", "centres_"], {"array": {"key": "nope"}}), "missing array"),
    "object dtype scalar": (_set(["state", "fitted", "dict", "x_"], {"scalar": {"dtype": "O", "value": 1}}),
                            "bad dtype"),
    "unknown tag": (_set(["state", "fitted", "dict", "x_"], {"call": "os.system"}), "unknown entry"),
    "two-key tag": (_set(["state", "fitted"], {"dict": {}, "tuple": []}), "unknown entry"),
    "deep nesting": (_set(["state", "fitted", "dict", "x_"], json.loads("[" * 200 + "]" * 200)), "nested deeper"),
    "training not a mapping": (_set(["training"], [1, 2]), "training record"),
    "state missing": (_set(["state"], None), "lacks a valid 'state'"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_DESCRIPTIONS))
def test_hostile_descriptions_are_refused_by_name(circles, tmp_path, case):
    edit, message = HOSTILE_DESCRIPTIONS[case]
    path = Centroid().fit(circles).save(tmp_path / "c.vtm")
    rewrite(path, edit)
    with pytest.raises(ModelFileError, match=message) as info:
        load_model(path)
    assert str(path) in str(info.value)


def _edit_array(key, change):
    def edit(description, arrays):
        arrays[key] = change(arrays[key])
    return edit


def _svc_key(description, name):
    return description["state"]["classify"]["calibrated"][0]["svc"]["dict"][name]["array"]["key"]


def _edit_svc(name, change):
    def edit(description, arrays):
        key = _svc_key(description, name)
        arrays[key] = change(arrays[key])
    return edit


HOSTILE_MODELS = {
    # CNN: stored tensors must match the architecture the header implies (checked on the meta device).
    ("cnn", "weight of another shape"): (_edit_array("cutaneous.fc1.weight", lambda a: a[:, :-1].copy()),
                                         "the architecture needs"),
    ("cnn", "NaN weight"): (_edit_array("kinesthetic.fc2.bias", lambda a: np.full_like(a, np.nan)), "NaN or Inf"),
    ("cnn", "extra tensor"): (lambda d, a: a.update({"cutaneous.extra": np.zeros(2, np.float32)}), "differ from"),
    ("cnn", "huge declared probes"): (_set(["probes"], 5_000), "the architecture needs"),
    ("cnn", "frame_std_ zero"): (_set(["state", "fitted", "dict", "frame_std_"], 0.0), "frame_std_"),
    ("cnn-kinesthetic", "modality without its net"): (_set(["params", "dict", "modality"], "fusion"),
                                                      "lacks a cutaneous net"),
    ("cnn", "unknown modality"): (_set(["params", "dict", "modality"], "smell"), "unknown modality"),
    # SVM: what libsvm would read out of bounds is checked first.
    ("svm", "support counts beyond the vectors"): (_edit_svc("_n_support", lambda a: a * 2), "support vector counts"),
    ("svm", "dual coefficients of another shape"): (_edit_svc("_dual_coef_", lambda a: a[:, :-1].copy()),
                                                     "_dual_coef_"),
    ("svm", "support vectors as float32"): (_edit_svc("support_vectors_", lambda a: a.astype(np.float32)),
                                            "support_vectors_"),
    ("svm", "k beyond the training set"): (_set(["state", "data_params", "classify__cv"], 10**6), "outside"),
    # kNN and the shared steps.
    ("knn", "labels out of range"): (lambda d, a: a.update({"knn.y": a["knn.y"] + 100}), "inconsistent"),
    ("knn", "selector mask of another length"): (
        lambda d, a: a.update({"pipeline.select.support_": a["pipeline.select.support_"][:-3].copy()}),
        "do not fit together"),
    ("knn", "missing step"): (lambda d, a: d["state"]["steps"].pop("zscore"), "steps are not"),
    ("knn", "unknown kind"): (_set(["params", "dict", "kind"], "tree"), "unknown classifier kind"),
}


@pytest.mark.parametrize("name,case", sorted(HOSTILE_MODELS))
def test_inconsistent_models_are_refused_before_use(models, tmp_path, name, case):
    edit, message = HOSTILE_MODELS[(name, case)]
    path = models[0][name].save(tmp_path / "m.vtm")
    rewrite(path, edit)
    with pytest.raises(ModelFileError, match=message):
        load_model(path)


def test_damaged_model_on_the_command_line_is_one_line_and_exit_2(circles, tmp_path, capsys):
    path = Centroid().fit(circles).save(tmp_path / "c.vtm")
    path.write_bytes(path.read_bytes()[:-5])
    assert main(["evaluate", "--model", str(path), "--store", str(tmp_path / "s.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "c.vtm" in err[0] and "visuotactile evaluate: error" in err[0]


class TestParameterNames:
    """Classifiers take scikit-learn's ``random_state``; files and scripts from before still work."""

    def test_a_file_that_names_the_seed_loads_as_random_state(self, models, tmp_path):
        cnn = models[0]["cnn"]
        path = cnn.save(tmp_path / "old.vtm")

        def old_names(description, arrays):
            params = description["params"]["dict"]
            params["seed"] = params.pop("random_state")

        rewrite(path, old_names)
        assert load_model(path).random_state == cnn.random_state

    def test_seed_keyword_is_random_state_with_a_warning(self):
        with pytest.warns(DeprecationWarning, match="random_state"):
            model = CNNClassifier(seed=4)
        assert model.random_state == 4 and "seed" not in model.get_params()
        with pytest.raises(TypeError, match="unexpected"):
            CNNClassifier(colour="red")

    def test_make_classifier_passes_options_on_and_takes_the_old_seed(self):
        from fusion.classifiers import make_classifier

        model = make_classifier("knn", reduce="pca", n_select=10, random_state=2)
        assert (model.reduce, model.n_select, model.random_state) == ("pca", 10, 2)
        with pytest.warns(DeprecationWarning):
            assert make_classifier("cnn", seed=5).random_state == 5


def test_a_header_length_that_starts_like_a_pickle_is_still_a_model_file():
    # A safetensors header of 640 + 256 k bytes begins 0x80 0x02..0x05: the bytes of a pickle's PROTO opcode. The
    # byte after the 8-byte length ('{') tells them apart (found when models began to record fingerprints).
    from fusion.modelfile import looks_like_pickle

    for length in (640, 896, 1152, 1408):
        assert not looks_like_pickle(length.to_bytes(8, "little") + b"{")
    assert looks_like_pickle(b"\x80\x04\x95\x10\x00\x00\x00\x00\x00")
    assert looks_like_pickle(b"\x80\x02}q\x00")
