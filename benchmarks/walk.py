"""The walk of one object through the house: ``visuotactile recognize`` -> Open3D ``cast_rays`` -> the decision.

A tiny case is built in-process: a catalogue object (``perception.shapes.make_object``) written to a temporary
PLY file and a small classifier trained on a few catalogue objects of two or three classes with a small FSR pad.
Then ``fusion.cli.main(["recognize", ...])`` runs under :func:`sys.setprofile`, which records every call into a
project module (``perception``, ``tactile``, ``fusion``) with the nearest project module up the stack that made
it, and every call of Open3D's ``RaycastingScene.cast_rays``.

It prints the project modules in the order they were first entered, each with its floor
(perception <- tactile <- fusion, see DESIGN.md) and the floors it was entered from, and flags

- a module entered from two different floors other than its own (the house has one door per room: fusion enters
  tactile through ``tactile.touching``, tactile enters perception's geometry; calls between modules of one
  floor are the floor's own business);
- an upward call: a perception or tactile module calling into a higher floor.

Three modules are shared by design and listed apart (:data:`SHARED`). A module's ``__getattr__`` (PEP 562: the
lookup of a name kept there for old imports, e.g. ``perception.geometry.load_object``) does not count as entering
it; the function found is what runs, in its own module.

``--json`` prints the same as one JSON object. Exit code 1 when anything is flagged.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import threading
from pathlib import Path

#: The floors, lowest first: a module may call into its own floor or lower ones only.
FLOORS = ("perception", "tactile", "fusion")

#: Modules every floor uses by design, with the reason; reported, not flagged, when entered from two floors.
SHARED = {
    "perception.errors": "the exception hierarchy every package raises (DESIGN.md section 6)",
    "perception.runtime": "the one progress switch (set by the command line, read by every loop) and the "
                          "version and machine information models and stores record",
    "perception.limits": "the size limits every floor checks before it allocates from a count it was given "
                         "(untrusted files, command-line counts, touch counts)",
}


def floor_of(module: str | None) -> str | None:
    """The floor of a module name (its top package), or None outside the project."""
    if not module:
        return None
    top = module.split(".", 1)[0]
    return top if top in FLOORS else None


class Walk:
    """A profiler that records the project modules entered, who entered them and who cast rays."""

    def __init__(self) -> None:
        self.order: list[str] = []  # first entry order
        self.callers: dict[str, dict[str, None]] = {}  # module -> ordered set of calling project modules
        self.cast_rays: dict[str, int] = {}  # module that called cast_rays -> calls
        self.cast_rays_at: int | None = None  # length of ``order`` at the first cast_rays

    @staticmethod
    def _project_module(frame) -> str | None:
        """The nearest project module at or above ``frame`` (None when there is none)."""
        while frame is not None:
            name = frame.f_globals.get("__name__")
            if floor_of(name):
                return name
            frame = frame.f_back
        return None

    def profile(self, frame, event, arg) -> None:
        if event == "call":
            module = frame.f_globals.get("__name__")
            if not floor_of(module) or frame.f_code.co_qualname == "__getattr__":
                return  # a module's __getattr__ only looks up a name kept for old imports (PEP 562)
            if module not in self.callers:
                self.callers[module] = {}
                self.order.append(module)
            caller = self._project_module(frame.f_back)
            if caller is not None and caller != module:
                self.callers[module][caller] = None
        elif event == "c_call" and getattr(arg, "__name__", None) == "cast_rays":
            caller = self._project_module(frame)
            if caller is not None:
                self.cast_rays[caller] = self.cast_rays.get(caller, 0) + 1
                if self.cast_rays_at is None:
                    self.cast_rays_at = len(self.order)

    @contextlib.contextmanager
    def recording(self):
        threading.setprofile(self.profile)
        sys.setprofile(self.profile)
        try:
            yield self
        finally:
            sys.setprofile(None)
            threading.setprofile(None)

    def report(self) -> dict:
        """The walk as a JSON-ready dict: modules in order (floor, entered from), flags."""
        modules, two_floors, shared, upward = [], [], [], []
        for module in self.order:
            floor = floor_of(module)
            callers = list(self.callers[module])
            floors = list(dict.fromkeys(floor_of(c) for c in callers))
            other = [f for f in floors if f != floor]
            modules.append({"module": module, "floor": floor, "entered_from": floors, "callers": callers,
                            "cast_rays": self.cast_rays.get(module, 0)})
            if len(other) > 1:
                (shared if module in SHARED else two_floors).append({"module": module, "floors": other,
                                   "callers": [c for c in callers if floor_of(c) != floor]})
            for caller in callers:
                if FLOORS.index(floor_of(caller)) < FLOORS.index(floor):
                    upward.append({"caller": caller, "callee": module})
        doors: dict[str, list[str]] = {}  # "upper -> lower": the lower floor's modules the upper one entered
        for module in self.order:
            for caller_floor in dict.fromkeys(floor_of(c) for c in self.callers[module]):
                if caller_floor != floor_of(module):
                    doors.setdefault(f"{caller_floor} -> {floor_of(module)}", []).append(module)
        return {"modules": modules, "cast_rays_after": self.cast_rays_at, "doors": doors, "two_floors": two_floors,
                "shared": [{**m, "reason": SHARED[m["module"]]} for m in shared], "upward": upward, "upward_imports": upward_imports()}


def upward_imports(root: Path | None = None) -> list[dict]:
    """Imports of a higher floor in the source of a lower one (read from the files, every module)."""
    import ast

    root = root or Path(__file__).resolve().parents[1]
    found = []
    for floor in FLOORS[:-1]:
        higher = FLOORS[FLOORS.index(floor) + 1:]
        for path in sorted((root / floor).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
            for node in ast.walk(tree):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
                for name in names:
                    if floor_of(name) in higher:
                        found.append({"file": str(path.relative_to(root)), "line": node.lineno, "imports": name})
    return found


def build_case(folder: Path, *, classes: tuple[str, ...] = ("mug", "box"), objects_per_class: int = 2,
               contours: int = 3, probes: int = 8, side: int = 16, kind: str = "knn") -> tuple[Path, Path]:
    """The tiny case in ``folder``: ``mug.ply`` (``make_object("mug", 0)``) and ``model.vtm`` (a
    ConventionalClassifier of ``kind`` trained on ``objects_per_class`` catalogue objects of each class, seeds from
    1, touched blind along ``contours`` contours of ``probes`` probes with a ``side`` x ``side`` pad)."""
    import open3d as o3d

    from fusion.conventional import ConventionalClassifier
    from fusion.experiments.touch import touch_objects
    from perception.shapes import make_object
    from tactile.sensor import FSRSensor

    mesh = folder / "mug.ply"
    if not o3d.io.write_triangle_mesh(str(mesh), make_object("mug", 0).to_open3d()):
        raise OSError(f"could not write {mesh}")
    seen = [make_object(c, s) for c in classes for s in range(1, objects_per_class + 1)]
    batch = touch_objects(seen, list(classes), "blind", contours, sensor=FSRSensor(rows=side, cols=side),
                          probes=probes)
    model = ConventionalClassifier(kind=kind, random_state=0).fit(batch)
    return mesh, model.save(folder / "model.vtm")


def walk(mesh: Path, model: Path, *, touches: int = 2, strategy: str = "guided", seed: int = 0) -> dict:
    """Run ``visuotactile recognize`` on ``mesh`` with ``model`` under the profiler; the walk and the decision."""
    from fusion.cli import main as cli

    argv = ["recognize", str(mesh), "--model", str(model), "--touches", str(touches), "--strategy", strategy,
            "--seed", str(seed), "--json"]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), Walk().recording() as recorder:
        code = cli(argv)
    if code != 0:
        raise RuntimeError(f"visuotactile {' '.join(argv)} exited {code}: {err.getvalue().strip()}")
    decision = json.loads(out.getvalue())
    return {"argv": ["visuotactile", *argv[:1], mesh.name, *argv[2:3], model.name, *argv[4:]],
            "label": decision["label"], **recorder.report()}


def _print(result: dict) -> None:
    print(f"walk of {' '.join(result['argv'])}: decided {result['label']!r}")
    print(f"{'#':>3}  {'module':<34} {'floor':<11} entered from")
    for i, m in enumerate(result["modules"], 1):
        if result["cast_rays_after"] == i - 1:
            print("     -- Open3D cast_rays first called here --")
        rays = f"  (cast_rays x{m['cast_rays']})" if m["cast_rays"] else ""
        print(f"{i:>3}  {m['module']:<34} {m['floor']:<11} {', '.join(m['callers']) or '-'}{rays}")
    for pair, entered in result["doors"].items():
        print(f"{pair}: {', '.join(entered)}")
    for m in result["two_floors"]:
        print(f"FLAG: {m['module']} entered from two floors: {', '.join(m['callers'])}")
    for m in result["shared"]:
        print(f"shared by design: {m['module']} entered from {', '.join(m['callers'])} ({m['reason']})")
    for u in result["upward"]:
        print(f"FLAG: upward call {u['caller']} -> {u['callee']}")
    for u in result["upward_imports"]:
        print(f"FLAG: upward import {u['file']}:{u['line']} imports {u['imports']}")
    if not (result["two_floors"] or result["upward"] or result["upward_imports"]):
        print("no module entered from two floors, no upward call or import")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="walk", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result instead of the list")
    parser.add_argument("--strategy", default="guided",
                        help="the recognize command's --strategy (default guided, the command's own)")
    parser.add_argument("--touches", type=int, default=2, help="the recognize command's --touches (default 2)")
    args = parser.parse_args(argv)
    from perception.errors import VisuotactileError
    from tactile.touching import check_strategy

    if args.touches < 1:  # checked before the case is built: exit 1 means a flag, not a bad argument
        parser.error(f"--touches must be a positive integer, got {args.touches}")
    try:
        check_strategy(args.strategy)
    except VisuotactileError as exc:
        parser.error(f"--strategy: {exc}")
    from perception.runtime import set_progress

    set_progress(False)
    try:
        with tempfile.TemporaryDirectory(prefix="walk-") as tmp:
            mesh, model = build_case(Path(tmp))
            result = walk(mesh, model, touches=args.touches, strategy=args.strategy)
    finally:
        set_progress(None)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        _print(result)
    return 1 if result["two_floors"] or result["upward"] or result["upward_imports"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
