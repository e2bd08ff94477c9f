"""Fork-after-threads deadlocks of isolated native calls, counted (``perception.isolate``).

A fork copies only the calling thread, so a child forked while one of Open3D's TBB workers was still in its task
arena waits for that worker for ever in its next parallel call. This benchmark makes the calls where that was
seen: the 148-point seed cloud of the file fuzzer (``benchmarks.fuzz``) through ``load_points`` (Poisson
surface in a forked child), in one process, after the same warm-up as a fuzz child, ``--calls`` times. It prints
how many children slept without using the CPU (presumed deadlocked: killed, and forked again while the call had
children left), how many calls failed, and the median and largest seconds per call.

``--attempts 1`` forks once per call, as before retries existed: each deadlock is then a failed call (before the
stall watch it waited out the call's 150 s limit). ``--json`` prints the same as one JSON object.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks._common import machine


class _Count(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.deadlocks = 0

    def emit(self, record: logging.LogRecord) -> None:
        self.deadlocks += "without using the CPU" in record.getMessage()


def run(calls: int, attempts: int, stall_s: float) -> dict:
    from benchmarks import fuzz
    from perception import isolate
    from perception.errors import VisuotactileError
    from perception.reconstruct.surface import load_points, points_to_model

    count = _Count()
    logging.getLogger("perception.isolate").addHandler(count)
    old = isolate.ATTEMPTS, isolate.STALL_S
    isolate.ATTEMPTS, isolate.STALL_S = attempts, stall_s
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "cloud.npz"
            path.write_bytes(next(s for s in fuzz.point_seeds() if s.name == "cloud.npz").data)
            points_to_model(fuzz._cloud()[0], **fuzz.POINT_KWARGS)  # the fuzz child's warm-up: TBB's workers start
            times, failures = [], []
            for _ in range(calls):
                start = time.perf_counter()
                try:
                    load_points(path, **fuzz.POINT_KWARGS)
                except VisuotactileError as exc:
                    failures.append(str(exc)[-160:])
                times.append(time.perf_counter() - start)
    finally:
        isolate.ATTEMPTS, isolate.STALL_S = old
        logging.getLogger("perception.isolate").removeHandler(count)
    return {"machine": machine(), "calls": calls, "attempts": attempts, "stall_s": stall_s,
            "deadlocked_children": count.deadlocks, "failed_calls": len(failures), "failures": failures[:5],
            "median_s": statistics.median(times), "max_s": max(times)}


def main(argv: list[str] | None = None) -> int:
    from fusion.commands import positive_int, positive_seconds

    parser = argparse.ArgumentParser(prog="python -m benchmarks.fork_stress", description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=positive_int, default=2000, help="isolated surface calls (default 2000)")
    parser.add_argument("--attempts", type=positive_int, default=None,
                        help="children forked per call at most (default perception.isolate.ATTEMPTS)")
    parser.add_argument("--stall-s", type=positive_seconds, default=None,
                        help="seconds asleep without CPU before a child is deadlocked (default isolate.STALL_S)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    from perception import isolate

    out = run(args.calls, args.attempts or isolate.ATTEMPTS,
              isolate.STALL_S if args.stall_s is None else args.stall_s)
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        print(f"{out['calls']} isolated Poisson calls, {out['attempts']} children per call at most, "
              f"stall limit {out['stall_s']:g} s")
        print(f"deadlocked children {out['deadlocked_children']}, failed calls {out['failed_calls']}, "
              f"seconds per call median {out['median_s']:.3f}, max {out['max_s']:.2f}")
        for failure in out["failures"]:
            print(f"  failed: ...{failure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
