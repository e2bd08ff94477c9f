"""The classifiers by name, for the CLI and the experiments: ``cnn`` (CNN pair, probability fusion),
``svm`` and ``knn`` (contourlet + wavelet features)."""

from __future__ import annotations

from perception.errors import InvalidArgumentError

CLASSIFIERS = ("cnn", "svm", "knn")


def make_classifier(name: str, *, cue: str = "invariant", random_state: int = 0, progress: bool = False, **options):
    """A new, unfitted classifier ``name`` with kinesthetic ``cue`` and ``random_state``; ``options`` go to its
    constructor.

    Raises:
        DatasetError: unknown name.
    """
    from fusion.base import renamed_seed

    if "seed" in options:  # the name before scikit-learn's; the other options go to the constructor
        random_state = renamed_seed({"seed": options.pop("seed")}, random_state, "make_classifier")
    if name == "cnn":
        from fusion.cnn import CNNClassifier

        return CNNClassifier(cue=cue, random_state=random_state, progress=progress, **options)
    if name in ("svm", "knn"):
        from fusion.conventional import ConventionalClassifier

        return ConventionalClassifier(kind=name, cue=cue, random_state=random_state, **options)
    raise InvalidArgumentError(f"unknown classifier {name!r}; choose one of {', '.join(CLASSIFIERS)}")


__all__ = ["CLASSIFIERS", "make_classifier"]
