"""Draw one contour on an object and its 25 tactile frames.

    .venv/bin/python examples/contour_figure.py [MESH] [--out out/contour.png] [--seed 0]

Without MESH the object is a built-in one (a procedural mug when the catalogue is there, else a torus).
"""

from __future__ import annotations

import argparse

import numpy as np

from perception.errors import ContourError
from perception.geometry import load_object
from tactile import FSRSensor, explore, make_contour, plane_through
from tactile.figures import plot_sequence


def builtin_object():
    try:
        from perception.shapes import make_object
    except ImportError:
        from perception.primitives import torus

        return torus(50.0, 20.0, 96, 48)
    return make_object("mug", seed=0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("mesh", nargs="?", help="mesh file (OFF, OBJ, PLY, STL); default: a built-in object")
    parser.add_argument("--out", default="out/contour.png", help="PNG to write")
    parser.add_argument("--seed", type=int, default=0, help="seed of the two random vertices of the plane")
    args = parser.parse_args(argv)
    model = load_object(args.mesh) if args.mesh else builtin_object()
    rng = np.random.default_rng(args.seed)
    while True:  # redraw near-collinear pairs
        i, j = rng.choice(model.n_vertices, 2, replace=False)
        try:
            plane = plane_through(model.center, model.vertices[i], model.vertices[j])
            break
        except ContourError:
            continue
    contour = make_contour(model, plane, n_probes=25)
    sequence = explore(model, contour, FSRSensor(), seed=args.seed)
    path = plot_sequence(model, contour, sequence, args.out)
    print(f"{model.name}: pad sides {np.round(sequence.pad_sides_mm, 1).tolist()} mm -> {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
