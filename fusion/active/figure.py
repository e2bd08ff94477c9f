"""One active episode as a figure: the object with the touched contours in order, and the posterior after each."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fusion.active.episode import Episode
from perception.atomic import save_figure
from perception.geometry import ObjectModel
from tactile.contours import section


def plot_episode(episode: Episode, model: ObjectModel, path: str | Path, *, label: str | None = None,
                 title: str | None = None) -> Path:
    """Left: ``model`` (the touched object, its vertices seen from the side, mm) with each touched contour drawn
    and numbered in touch order; right: the fused posterior over the classes after each touch (rows), the true
    class ``label`` marked when given. Returns the written path."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.5), layout="constrained")
    ax, bx = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.4]})
    v = model.vertices[:: max(1, model.n_vertices // 3000)]
    ax.scatter(v[:, 0], v[:, 2], s=0.3, c="0.75", rasterized=True)
    colours = colormaps["viridis"](np.linspace(0, 0.9, max(episode.touches, 1)))
    for k, plane in enumerate(episode.planes):
        lines = section(model, plane)
        for line in lines:
            ax.plot(line[:, 0], line[:, 2], "-", lw=1.4, color=colours[k])
        if lines:
            top = max(lines, key=len)
            i = int(np.argmax(top[:, 2]))
            ax.annotate(str(k + 1), (top[i, 0], top[i, 2]), color=colours[k], fontsize=10, weight="bold")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title(f"{model.name}: touches in order ({episode.policy})")
    post = episode.posteriors
    im = bx.imshow(post, aspect="auto", cmap="Blues", vmin=0, vmax=1)
    bx.set_xticks(range(len(episode.classes)), episode.classes, rotation=45, ha="right")
    bx.set_yticks(range(len(post)), [f"after {k + 1}" for k in range(len(post))])
    for k in range(len(post)):
        j = int(np.argmax(post[k]))
        bx.text(j, k, f"{post[k, j]:.2f}", ha="center", va="center", fontsize=8,
                color="white" if post[k, j] > 0.5 else "black")
    if label in episode.classes:
        bx.axvline(episode.classes.index(label), color="tab:red", lw=1, ls="--")
    bx.set_title(title or f"posterior after each touch (log rule); decision: {episode.decision}")
    fig.colorbar(im, ax=bx, fraction=0.04)
    return save_figure(fig, Path(path))


def demo_episode(out: str | Path, classifier, *, class_name: str = "mug", instance_seed: int = 3, seed: int = 0,
                 touches: int = 4, candidates: int = 12) -> dict:
    """``make demo``'s active episode: catalogue instance ``(class_name, instance_seed)`` (one nobody trained on),
    its visual model a 1 mm noisy copy, ``touches`` touches planned by the information policy (``candidates`` x 1
    variant), drawn to ``out/active_episode.png``. Returns what the report needs."""
    import time

    from fusion.active import make_policy, noisy_copy, run_episode
    from perception.shapes import make_object

    start = time.perf_counter()
    true = make_object(class_name, instance_seed)
    episode = run_episode(true, noisy_copy(true, 1.0, seed=seed), classifier,
                          make_policy("information", seed, candidates=candidates, variants=1),
                          max_touches=touches, seed=seed)
    path = plot_episode(episode, true, Path(out) / "active_episode.png", label=class_name)
    return {"figure": path.name, "object": true.name, "decisions": episode.decisions(),
            "posterior_true": [round(float(p[episode.classes.index(class_name)]), 3) for p in episode.posteriors],
            "seconds": round(time.perf_counter() - start, 1)}


__all__ = ["demo_episode", "plot_episode"]
