"""Figures of a contour exploration: the contour on the object and its tactile frames.

Drawn on ``matplotlib.figure.Figure`` objects and written through the Agg canvas directly: importing this
module or drawing never touches pyplot or the user's matplotlib backend."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from perception.atomic import save_figure
from perception.geometry import ObjectModel
from tactile.contours import Contour
from tactile.explore import TactileSequence

#: Above this many triangles the mesh is drawn as a vertex scatter (trisurf gets slow).
MAX_TRISURF_TRIANGLES = 20000


def plot_sequence(model: ObjectModel, contour: Contour, sequence: TactileSequence, path: str | Path) -> Path:
    """Draw the contour and probes on the object (3D) next to the sequence's frames as an image grid
    (5 x 5 for 25 probes, shared colour scale, pad side in each title); write a PNG to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = sequence.n_probes
    grid_cols = math.ceil(math.sqrt(n))
    grid_rows = math.ceil(n / grid_cols)
    fig = Figure(figsize=(6 + 1.4 * grid_cols, max(5.0, 1.4 * grid_rows)))
    FigureCanvasAgg(fig)
    outer = fig.add_gridspec(1, 2, width_ratios=[6, 1.4 * grid_cols])
    ax = fig.add_subplot(outer[0], projection="3d")
    v = model.vertices
    if model.n_triangles <= MAX_TRISURF_TRIANGLES:
        ax.plot_trisurf(
            v[:, 0], v[:, 1], v[:, 2], triangles=model.triangles, color="0.85", alpha=0.25, linewidth=0
        )
    else:
        step = max(1, len(v) // 5000)
        ax.scatter(*v[::step].T, s=0.5, c="0.6", alpha=0.3)
    loop = np.vstack([contour.polyline, contour.polyline[:1]]) if contour.closed else contour.polyline
    ax.plot(*loop.T, color="tab:red", linewidth=1.5)
    ax.scatter(*contour.positions.T, color="tab:blue", s=12, depthshade=False)
    ax.quiver(
        *contour.positions.T, *(contour.normals * 0.06 * model.diagonal).T, color="tab:blue", linewidth=0.6
    )
    ax.scatter(*contour.positions[:1].T, color="black", s=30, depthshade=False)  # the first probe
    lo, hi = model.bounds
    half = 0.5 * (hi - lo).max()
    for setter, centre in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), 0.5 * (lo + hi)):
        setter(centre - half, centre + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x mm")
    ax.set_ylabel("y mm")
    ax.set_zlabel("z mm")
    ax.set_title(f"{sequence.object_name}: {n} probes")
    frames = sequence.frames
    inner = outer[1].subgridspec(grid_rows, grid_cols, wspace=0.05, hspace=0.35)
    vmin, vmax = float(frames.min()), float(max(frames.max(), frames.min() + 1e-6))
    image = None
    for k in range(grid_rows * grid_cols):
        sub = fig.add_subplot(inner[k // grid_cols, k % grid_cols])
        sub.set_axis_off()
        if k < n:
            image = sub.imshow(frames[k], cmap="viridis_r", vmin=vmin, vmax=vmax, origin="lower")
            sub.set_title(f"{k}: {sequence.pad_sides_mm[k]:.3g} mm", fontsize=6)
    if image is not None:
        fig.colorbar(image, ax=fig.axes[1:], shrink=0.6, label="gap mm" if frames.max() > 1.5 else "reading")
    save_figure(fig, path, dpi=120, bbox_inches="tight")
    return path


__all__ = ["plot_sequence"]
