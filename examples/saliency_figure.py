"""Saliency figures for one object: per-view channel maps, and the per-vertex saliency of each method.

    .venv/bin/python examples/saliency_figure.py [MESH_FILE | CLASS_NAME] [--out FOLDER]

With no argument it uses a built-in mug (``perception.shapes``); a file path loads that mesh.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from perception.geometry import load_object
from perception.saliency import METHODS, plot_channels, plot_saliency, saliency


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("object", nargs="?", default="mug", help="a mesh file or a built-in class name")
    parser.add_argument("--out", type=Path, default=Path("out/saliency"), help="output folder")
    args = parser.parse_args(argv)
    if Path(args.object).is_file():
        model = load_object(args.object)
    else:
        from perception.shapes import make_object

        model = make_object(args.object, 0)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = model.name.replace("/", "_")
    print(plot_channels(model, args.out / f"{stem}_channels.png"))
    for method in METHODS:
        print(plot_saliency(saliency(model, method), args.out / f"{stem}_{method}.png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
