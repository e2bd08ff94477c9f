"""A fuzzer for the files people and robots exchange, run through the command line: dataset stores, model files and
camera recordings (the mesh and point-cloud loaders have :mod:`benchmarks.fuzz`).

Seeds, made once per run: a small store (2 catalogue objects x 4 blind contours, 6 probes, 8 x 8 taxels), a kNN
model trained on it (``visuotactile train --split none``), the clean ``evaluate --json`` result of that pair, and a
one-frame recording (32 x 24). Families of cases:

- ``store_meta``: a field of the store's ``zarr.json`` (settings, sensor, encoding, objects, array metadata) set to a
  hostile value (None, text, negative, 0, 1e8, 1e12, a float, a list, an object, a bool) or deleted;
- ``store_chunk``: a chunk file of an array flipped, truncated, emptied, deleted or swapped with another;
- ``store_record``: an object's completion record edited, emptied or deleted;
- ``model_bytes``: the model file flipped, truncated, extended, or cut at its header;
- ``model_header``: the JSON description rewritten with a valid checksum (hostile but consistent), as above;
- ``model_payload``: pickles whose loading would create a marker file (``os.system``, ``builtins.exec``, a
  ``__reduce__`` chain), under ``.vtm`` and ``.pkl`` names, alone or behind a safetensors-like header; run through
  ``evaluate --model``, ``recognize --model`` and ``camera --model``;
- ``recording``: the recording's index or frame JSON given hostile values, frame names pointing elsewhere, PNGs
  flipped, truncated, swapped or replaced by images whose header claims up to 30000 x 30000 pixels.

Store and model cases run ``visuotactile evaluate --model M --store S --json``; recording cases ``visuotactile camera
--source R --json``. Every case runs in a child process (``python -m benchmarks.fuzz_files --child``, many cases
per child, through :func:`fusion.cli.main`) under an address-space limit (``RLIMIT_AS`` = the child's size after
start-up + ``--memory-mb``; the toolkit's own ``VISUOTACTILE_MAX_MEMORY_MB`` is set to half of that, as on a robot
with little memory) and a CPU-time limit. Outcomes:

- ``refused``: exit 2 with exactly one line on stderr; ``ok``: exit 0 (for a store or model whose data bytes were
  damaged, only with the clean result; see ``wrong``);
- ``foreign``: an exception escaped ``main`` (a traceback), an exit code not in {0, 2}, or exit 2 with other than one
  line; ``memory``: a MemoryError (the address-space limit was hit); ``crash``: the child died; ``timeout``;
- ``payload``: a planted payload ran (its marker file exists);
- ``wrong``: a silent wrong result: exit 0 on a store or model file whose bytes were damaged (``store_chunk``,
  ``store_record`` edits of digests aside, ``model_bytes``), or any exit-0 evaluation whose numbers differ from the
  clean store's.

    .venv/bin/python -m benchmarks.fuzz_files [--cases 1000] [--seed S] [--memory-mb 1024] [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import pickle
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from benchmarks.fuzz import CHILDREN, _reset_peak, _status_kb, outcome_summary, outcome_table, supervise_child

ROOT = Path(__file__).resolve().parents[1]
FAMILIES = ("store_meta", "store_chunk", "store_record", "model_bytes", "model_header", "model_payload", "recording")
#: Share of the cases per family (they add up to 1).
SHARES = {"store_meta": 0.2, "store_chunk": 0.17, "store_record": 0.08, "model_bytes": 0.14, "model_header": 0.14,
          "model_payload": 0.07, "recording": 0.2}
OUTCOMES = ("ok", "refused", "foreign", "memory", "crash", "timeout", "payload", "wrong")
PASSING = frozenset({"ok", "refused"})
HOSTILE = (None, "x", "", -1, 0, 1, 10**8, 10**12, 2**63, -(2**63), 1.5, 1e308, True, [], [1, 2], {}, {"a": 1},
           "NaN", "../../etc/passwd")


@dataclass
class Case:
    family: str
    command: list[str]  # the CLI arguments
    note: str
    damaged: bool = False  # data bytes damaged: exit 0 is a silent wrong result
    marker: str | None = None  # a payload's marker file
    compare: bool = False  # exit 0 must give the clean evaluation


@dataclass
class Result:
    case: Case
    outcome: str
    detail: str
    seconds: float
    peak_mb: float
    numbers: dict | None = None  # an exit-0 evaluation's decisions, accuracy and per-class accuracy


# ------------------------------------------------------------------------------------------------ seeds
def make_seeds(folder: Path) -> dict:
    """The clean store, model, recording and the clean evaluation (the child's code path, once, in a child)."""
    folder.mkdir(parents=True, exist_ok=True)
    script = f"""
import json, sys
import numpy as np
from fusion.cli import main
from perception.camera import Intrinsics, RGBDFrame, write_recording
from tactile.dataset import generate
from tactile.sensor import FSRSensor
folder = {str(folder)!r}
generate([("box", 0), ("ring", 0)], folder + "/store.zarr", strategies="blind", contours_per_object=4,
         sensor=FSRSensor(rows=8, cols=8), probes=6, seed=0, workers=1, progress=False, command="fuzz seed")
assert main(["train", "--store", folder + "/store.zarr", "--model", "knn", "--out", folder + "/model.vtm",
             "--split", "none", "--no-progress"]) == 0
color = np.full((24, 32, 3), 128, np.uint8)
depth = np.full((24, 32), 500.0, np.float32)
depth[8:16, 10:22] = 450.0
frame = RGBDFrame(color, depth, Intrinsics(fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24), np.eye(4), 0.0,
                  name="f")
write_recording(folder + "/recording", [frame])
"""
    subprocess.run([sys.executable, "-c", script], cwd=ROOT, check=True, capture_output=True,
                   env={**os.environ, "PYTHONPATH": str(ROOT)})
    return {"store": folder / "store.zarr", "model": folder / "model.vtm", "recording": folder / "recording"}


def _evaluate(model: Path, store: Path) -> list[str]:
    return ["evaluate", "--model", str(model), "--store", str(store), "--json", "--no-progress"]


def _camera(recording: Path, out: Path, model: Path | None = None) -> list[str]:
    return ["camera", "--source", str(recording), "--out", str(out), "--json", "--no-progress", "--contours", "2",
            "--views", "1"] + (["--model", str(model)] if model else [])


def _set_path(node, keys, value, delete: bool) -> None:
    for key in keys[:-1]:
        node = node[key]
    if delete:
        if isinstance(node, dict):
            node.pop(keys[-1], None)
        elif isinstance(node, list) and node:
            node.pop(keys[-1])
    else:
        node[keys[-1]] = value


def _paths(node, prefix=()) -> list[tuple]:
    """Every key path in a JSON document (lists: their first two items)."""
    out = []
    if isinstance(node, dict):
        for k, v in node.items():
            out.append((*prefix, k))
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node[:2]):
            out.append((*prefix, i))
            out += _paths(v, (*prefix, i))
    return out


def _mutate_json(path: Path, rng: np.random.Generator, only=None) -> str:
    doc = json.loads(path.read_text())
    paths = [p for p in _paths(doc) if only is None or only(p)] or [()]
    keys = paths[int(rng.integers(len(paths)))]
    if not keys:
        path.write_text(json.dumps(HOSTILE[int(rng.integers(len(HOSTILE)))]))
        return f"{path.name}: whole document replaced"
    delete = rng.random() < 0.2
    value = HOSTILE[int(rng.integers(len(HOSTILE)))]
    _set_path(doc, list(keys), value, delete)
    path.write_text(json.dumps(doc))
    return f"{path.name}: {'/'.join(map(str, keys))} " + ("deleted" if delete else f"= {value!r}"[:60])


def _flip(data: bytes, rng) -> tuple[bytes, str]:
    if not data:
        return b"\0", "empty -> one byte"
    b = bytearray(data)
    n = int(rng.integers(1, 4))
    where = rng.integers(0, len(b), n)
    for i in where:
        b[i] ^= 1 << int(rng.integers(8))
    return bytes(b), f"{n} bit(s) flipped at {sorted(int(i) for i in where)}"


def _damage_file(path: Path, rng, others: list[Path]) -> str:
    data = path.read_bytes()
    kind = ("flip", "flip", "truncate", "empty", "delete", "swap", "append")[int(rng.integers(7))]
    if kind == "flip":
        new, note = _flip(data, rng)
        path.write_bytes(new)
        return note
    if kind == "truncate":
        cut = int(rng.integers(0, max(len(data), 1)))
        path.write_bytes(data[:cut])
        return f"truncated to {cut} of {len(data)} bytes"
    if kind == "empty":
        path.write_bytes(b"")
        return "emptied"
    if kind == "delete":
        path.unlink()
        return "deleted"
    if kind == "swap":
        other = next((o for o in others if o.read_bytes() != data), None)
        if other is None:
            path.write_bytes(data[::-1])
            return "reversed"
        path.write_bytes(other.read_bytes())
        return f"replaced by {other.name}"
    path.write_bytes(data + bytes(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8)))
    return "bytes appended"


def _png_header(width: int, height: int, color_type: int, depth: int) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    channels = {0: 1, 2: 3}[color_type] * depth // 8
    row = b"\0" * (1 + min(width, 1 << 16) * channels)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, color_type, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(row)) + chunk(b"IEND", b""))


class _Payload:
    """Pickled, its loading runs ``os.system("touch MARKER")``."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _payloads(marker: str) -> list[tuple[str, bytes]]:
    code = f"open({marker!r}, 'w').close()"
    plain = pickle.dumps(_Payload(marker), protocol=2)
    exec_pickle = b"cbuiltins\nexec\n(V" + code.encode() + b"\ntR."
    nested = pickle.dumps({"model": _Payload(marker), "classes": ["a", "b"]}, protocol=4)
    fake_header = struct.pack("<Q", 2) + b"{}" + plain  # safetensors-like length prefix, then the pickle
    torch_like = b"PK\x03\x04" + plain
    return [("os.system", plain), ("builtins.exec", exec_pickle), ("nested", nested),
            ("behind a header", fake_header), ("zip-like", torch_like)]


def make_cases(folder: str | Path, n_cases: int, *, seed: int = 0, seeds: dict | None = None) -> list[Case]:
    """``n_cases`` cases, split between the families by :data:`SHARES`, each with its own copy of what it damages."""
    folder = Path(folder)
    seeds = seeds or make_seeds(folder / "seeds")
    rng = np.random.default_rng(seed)
    store, model, recording = seeds["store"], seeds["model"], seeds["recording"]
    counts = {f: max(1, round(SHARES[f] * n_cases)) for f in FAMILIES}
    counts["store_meta"] += n_cases - sum(counts.values())
    cases: list[Case] = []
    for family in FAMILIES:
        for k in range(counts[family]):
            where = folder / f"{family}-{k:04d}"
            where.mkdir(parents=True)
            cases.append(_make_case(family, where, rng, store, model, recording))
    return cases


def _make_case(family: str, where: Path, rng, store: Path, model: Path, recording: Path) -> Case:
    if family.startswith("store"):
        copy = where / "store.zarr"
        shutil.copytree(store, copy)
        if family == "store_meta":
            files = [copy / "zarr.json"] * 3 + sorted(copy.glob("*/zarr.json"))
            target = files[int(rng.integers(len(files)))]
            note = _mutate_json(target, rng)
            return Case(family, _evaluate(model, copy), f"{target.relative_to(copy)}: {note}", compare=True)
        if family == "store_chunk":
            chunks = sorted(p for p in copy.rglob("*") if p.is_file() and "/c/" in p.relative_to(copy).as_posix())
            if rng.random() < 0.3:  # the frames shards hold most of the bytes: a third of the cases damage them
                chunks = [c for c in chunks if c.relative_to(copy).parts[0] == "frames"]
            target = chunks[int(rng.integers(len(chunks)))]
            note = _damage_file(target, rng, [c for c in chunks if c.parent.parent == target.parent.parent])
            return Case(family, _evaluate(model, copy), f"{target.relative_to(copy)}: {note}", damaged=True,
                        compare=True)
        records = sorted((copy / "records").glob("*.json"))
        target = records[int(rng.integers(len(records)))]
        if rng.random() < 0.5:
            note = _mutate_json(target, rng, only=lambda p: p[0] != "digests")
        else:
            note = _damage_file(target, rng, records)
        # Edited records may legitimately drop an object (status "failed", deleted): such a store evaluates the
        # others; exit 0 must then give the clean result or fewer decisions, never other numbers for the same ones.
        return Case(family, _evaluate(model, copy), f"{target.name}: {note}", compare=True)
    if family == "model_bytes":
        copy = where / "model.vtm"
        data = model.read_bytes()
        head = struct.unpack("<Q", data[:8])[0] + 8
        kind = int(rng.integers(4))
        if kind == 0:
            new, note = _flip(data, rng)
        elif kind == 1:
            cut = int(rng.integers(0, len(data)))
            new, note = data[:cut], f"truncated to {cut} of {len(data)} bytes"
        elif kind == 2:
            i = int(rng.integers(8, head))
            new, note = _flip(data[:head], rng)[0] + data[head:], f"header bits flipped (header {head} bytes, near {i})"
        else:
            new, note = data + bytes(rng.integers(0, 256, 16, dtype=np.uint8)), "16 bytes appended"
        copy.write_bytes(new)
        return Case(family, _evaluate(copy, store), note, damaged=new != data, compare=True)
    if family == "model_header":
        from safetensors import safe_open
        from safetensors.numpy import save

        from fusion.modelfile import FORMAT_NAME, content_digest

        copy = where / "model.vtm"
        with safe_open(str(model), framework="numpy") as f:
            arrays = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 -- a safe_open, not a dict
            text = f.metadata()[FORMAT_NAME].partition(" ")[2]
        tmp = where / "description.json"
        tmp.write_text(text)
        note = _mutate_json(tmp, rng)
        text = tmp.read_text()
        copy.write_bytes(save(arrays, metadata={FORMAT_NAME: f"{content_digest(text, arrays)} {text}"}))
        return Case(family, _evaluate(copy, store), f"description {note}")
    if family == "model_payload":
        marker = where / "PAYLOAD-RAN"
        options = _payloads(str(marker))
        name, data = options[int(rng.integers(len(options)))]
        path = where / ("model.vtm" if rng.random() < 0.5 else "model.pkl")
        path.write_bytes(data)
        command = (_evaluate(path, store), ["recognize", str(where / "x.off"), "--model", str(path), "--strategy",
                                            "blind", "--touches", "1"], _camera(recording, where / "out", path))
        pick = int(rng.integers(3))
        return Case(family, command[pick], f"{name} pickle as {path.name} via {command[pick][0]}",
                    marker=str(marker))
    # recording
    copy = where / "recording"
    shutil.copytree(recording, copy)
    frame = json.loads((copy / "recording.json").read_text())["frames"][0]
    kind = int(rng.integers(5))
    if kind == 0:
        note = _mutate_json(copy / "recording.json", rng)
    elif kind == 1:
        note = _mutate_json(copy / f"{frame}.json", rng)
    elif kind == 2:
        png = copy / f"{frame}.{'color' if rng.random() < 0.5 else 'depth'}.png"
        note = f"{png.name}: " + _damage_file(png, rng, sorted(copy.glob("*.png")))
    elif kind == 3:
        side = int((500, 4000, 7000, 9000, 16000, 30000)[int(rng.integers(6))])
        for part, (ctype, depth) in (("color", (2, 8)), ("depth", (0, 16))):
            (copy / f"{frame}.{part}.png").write_bytes(_png_header(side, side, ctype, depth))
        meta = json.loads((copy / f"{frame}.json").read_text())
        meta.update(width=side, height=side)
        (copy / f"{frame}.json").write_text(json.dumps(meta))
        note = f"images claim {side} x {side} pixels"
    else:
        index = json.loads((copy / "recording.json").read_text())
        target = ("../" + frame, "/etc/passwd", "..", f"{frame}/../{frame}", "frame_0000009", "")[int(rng.integers(6))]
        index["frames"] = [target]
        (copy / "recording.json").write_text(json.dumps(index))
        note = f"frame name {target!r}"
    return Case(family, _camera(copy, where / "out"), note)


# ------------------------------------------------------------------------------------------------- the child
def _child(manifest: str, start: int, fd: int, memory_mb: int) -> None:
    import faulthandler
    import logging
    import resource

    faulthandler.enable()
    out = os.fdopen(fd, "w", buffering=1)
    cases = [Case(**c) for c in json.loads(Path(manifest).read_text())]
    from fusion.cli import main

    # Warm up every path (imports, thread pools, allocator arenas) before the limit, so that it bounds the cases.
    warm = Path(manifest).parent / "warm"
    for argv in (["bench"], ["evaluate", "--model", "none.vtm", "--store", "none.zarr"],
                 ["camera", "--source", str(warm), "--views", "1"]):
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
                contextlib.suppress(BaseException):
            main(argv)
    import fusion.base  # noqa: F401
    import perception.reconstruct.tabletop  # noqa: F401
    import tactile.dataset  # noqa: F401

    limit = _status_kb("VmSize") * 1024 + memory_mb * 2**20
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    out.write(json.dumps({"ready": True, "rss_mb": _status_kb("VmRSS") / 1024, "limit_mb": limit / 2**20}) + "\n")
    for i in range(start, len(cases)):
        case = cases[i]
        _reset_peak()
        for handler in list(logging.root.handlers):  # basicConfig in main binds the stderr of this case
            logging.root.removeHandler(handler)
        began = time.perf_counter()
        stdout, stderr = io.StringIO(), io.StringIO()
        code, escaped = None, None
        try:
            with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
                code = main(list(case.command))
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except MemoryError as exc:
            escaped = ("memory", f"MemoryError: {exc}")
        except BaseException as exc:  # noqa: BLE001 -- what the fuzzer looks for
            import traceback

            where = traceback.extract_tb(exc.__traceback__)[-1]
            escaped = ("foreign", f"{type(exc).__name__}: {exc} (at {Path(where.filename).name}:{where.lineno})")
        lines = [ln for ln in stderr.getvalue().splitlines() if ln.strip()
                 and not ln.startswith(("WARNING ", "[Open3D WARNING]"))]
        record = {"i": i, "seconds": time.perf_counter() - began, "peak_mb": _status_kb("VmHWM") / 1024,
                  "code": code, "stdout": stdout.getvalue()[-4000:], "stderr": lines[-3:], "escaped": escaped,
                  "payload": bool(case.marker and os.path.exists(case.marker))}
        out.write(json.dumps(record, default=str) + "\n")
    out.close()


# ------------------------------------------------------------------------------------------------ the parent
def _numbers(stdout: str) -> dict | None:
    try:
        result = json.loads(stdout)
    except ValueError:
        return None
    return {k: result.get(k) for k in ("decisions", "accuracy", "per_class", "subset")}


def classify(case: Case, record: dict) -> tuple[str, str]:
    """The outcome of one case from what its child reported (exit-0 numbers are judged later, :func:`judge`)."""
    if record["payload"]:
        return "payload", "the planted payload ran"
    if record["escaped"]:
        return tuple(record["escaped"])  # type: ignore[return-value]
    code, err = record["code"], record["stderr"]
    if code == 2:
        if len(err) == 1:
            return "refused", err[0][:300]
        return "foreign", f"exit 2 with {len(err)} lines on stderr: {' | '.join(err)[:300]}"
    if code != 0:
        return "foreign", f"exit {code}: {' | '.join(err)[:300]}"
    if case.damaged:
        return "wrong", "a damaged file evaluated (exit 0)"
    return "ok", ""


def judge(results: list[Result], clean: dict) -> None:
    """Exit-0 evaluations must give the clean store's numbers (an edited record may drop its object: then fewer
    decisions); anything else is a silent wrong result."""
    for r in results:
        if r.outcome != "ok" or not r.case.compare:
            continue
        if r.numbers != clean:
            if r.case.family == "store_record" and r.numbers and (r.numbers.get("decisions") or 0) < clean["decisions"]:
                r.detail = "the object of the edited record is left out"
                continue
            r.outcome, r.detail = "wrong", f"exit 0 with other numbers than the clean store: {json.dumps(r.numbers)[:200]}"


def run_cases(cases: list[Case], *, timeout_s: float = 60.0, memory_mb: int = 1024, progress=None) -> list[Result]:
    """Run ``cases`` in child processes (many per child); a child that crashes or overruns is replaced."""
    results: list[Result | None] = [None] * len(cases)
    with tempfile.TemporaryDirectory(prefix="fuzz-files-") as tmp:
        manifest = Path(tmp) / "cases.json"
        manifest.write_text(json.dumps([asdict(c) for c in cases]))
        start = 0
        while start < len(cases):
            start = _run_child(manifest, cases, start, results, timeout_s, memory_mb, Path(tmp), progress)
    return results  # type: ignore[return-value]


def _run_child(manifest, cases, start, results, timeout_s, memory_mb, tmp, progress) -> int:
    """One child from case ``start`` on (see :func:`benchmarks.fuzz.supervise_child`)."""
    def result(i: int, record: dict) -> Result:
        outcome, detail = classify(cases[i], record)
        numbers = _numbers(record["stdout"]) if record["code"] == 0 else None
        return Result(cases[i], outcome, detail, record["seconds"], record["peak_mb"], numbers)

    env = {**os.environ, "OMP_NUM_THREADS": "1", "MALLOC_ARENA_MAX": "2", "PYTHONPATH": str(ROOT),
           "VISUOTACTILE_MAX_MEMORY_MB": str(max(memory_mb // 2, 64)), "VISUOTACTILE_PROGRESS": "0"}
    return supervise_child("benchmarks.fuzz_files", manifest, start, memory_mb, cwd=tmp, env=env, cases=cases,
                           results=results, result=result, result_type=Result, timeout_s=timeout_s, startup_s=300.0,
                           log_path=tmp / f"child-{start}.log", progress=progress)


# ------------------------------------------------------------------------------------------------- reporting
def summarize(results: list[Result]) -> dict:
    """Per family (:func:`benchmarks.fuzz.outcome_summary`)."""
    return outcome_summary(results, lambda r: r.case.family, OUTCOMES,
                           lambda name: FAMILIES.index(name) if name in FAMILIES else 99)


def failures(results: list[Result]) -> list[Result]:
    return [r for r in results if r.outcome not in PASSING]


def format_table(summary: dict) -> str:
    return outcome_table(summary, OUTCOMES, "family")


def fuzz(n_cases: int, *, seed: int = 0, memory_mb: int = 1024, timeout_s: float = 60.0, folder=None,
         progress=None) -> tuple[list[Result], dict]:
    """Make the seeds and ``n_cases`` cases in ``folder`` (default: a temporary one) and run them.
    Returns (results, the clean evaluation)."""
    with contextlib.ExitStack() as stack:
        if folder is None:
            folder = stack.enter_context(tempfile.TemporaryDirectory(prefix="fuzz-files-cases-"))
        folder = Path(folder)
        seeds = make_seeds(folder / "seeds")
        (folder / "seeds" / "x.off").write_text("OFF\n0 0 0\n")
        cases = make_cases(folder / "cases", n_cases, seed=seed, seeds=seeds)
        # The first case is the clean evaluation: its numbers are what every exit-0 store case must give.
        clean_case = Case("clean", _evaluate(seeds["model"], seeds["store"]), "clean")
        results = run_cases([clean_case, *cases], timeout_s=timeout_s, memory_mb=memory_mb, progress=progress)
        first, rest = results[0], results[1:]
        if first.outcome != "ok" or not first.numbers:
            raise RuntimeError(f"the clean store does not evaluate: {first.outcome}: {first.detail}")
        judge(rest, first.numbers)
        return rest, first.numbers


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        _child(argv[1], int(argv[2]), int(argv[3]), int(argv[4]))
        return 0
    parser = argparse.ArgumentParser(prog="fuzz_files", description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=1000, help="cases (default 1000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=60.0, help="CPU seconds per case (default 60)")
    parser.add_argument("--memory-mb", type=int, default=1024, help="address space a case may add (default 1024)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    began = time.perf_counter()
    results, _ = fuzz(args.cases, seed=args.seed, memory_mb=args.memory_mb, timeout_s=args.timeout)
    summary = summarize(results)
    bad = failures(results)
    peaks = [r.peak_mb for r in results if np.isfinite(r.peak_mb)]
    totals = {o: sum(r.outcome == o for r in results) for o in OUTCOMES}
    if args.json:
        print(json.dumps({"benchmark": "fuzz_files", "cases": len(results), "seconds": time.perf_counter() - began,
                          "memory_mb": args.memory_mb, "timeout_s": args.timeout, "totals": totals,
                          "peak_mb": {"median": float(np.median(peaks)), "max": float(np.max(peaks))},
                          "children": CHILDREN, "summary": summary,
                          "failures": [{**asdict(r.case), "outcome": r.outcome, "detail": r.detail} for r in bad]},
                         indent=1, default=str))
    else:
        print(format_table(summary))
        print(f"\n{len(results)} cases in {time.perf_counter() - began:.0f} s, {len(CHILDREN)} child process(es); per "
              f"case <= {args.timeout:g} CPU s and <= {args.memory_mb} MB of address space above the child's start-up "
              f"size (RSS {CHILDREN[0]['rss_mb']:.0f} MB, limit {CHILDREN[0]['limit_mb']:.0f} MB); peak RSS per case "
              f"median {np.median(peaks):.0f} MB, max {np.max(peaks):.0f} MB")
        for r in bad:
            print(f"FAIL {r.case.family} ({r.case.note}): {r.outcome}: {r.detail}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
