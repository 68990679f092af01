"""Run time of a call once compiled: the second (and later) calls of an entry in one process.

    python bench/profile_second_call.py build:sbvh twolevel:build collapse:optimal [--repeat 5]

Each entry of :mod:`bench.bench_compile` (same setup and call source) runs once (compiles,
or loads from jaxbvh's compile cache: set ``JAXBVH_CACHE_DIR`` to reuse one between runs),
then ``--repeat`` more times; printed: the minimum and the median of the later calls' CPU
seconds (``getrusage`` user + sys, all threads) and wall seconds, and the load average.
One JSON line per entry.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("entries", nargs="+")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    import jax
    import jaxbvh
    from bench.bench_compile import entries
    from jaxbvh.io import bundled_mesh_path

    table = entries(str(bundled_mesh_path()), "spot")
    for entry in args.entries:
        spec = table[entry]
        scope = {"spec": {"mesh": str(bundled_mesh_path())}, "jax": jax, "jaxbvh": jaxbvh}
        setup = spec["setup"]
        if "tree" in setup:  # a sweep tree, as bench_compile prepares it
            setup = ("from jaxbvh.io import load_mesh\nmesh = load_mesh(spec['mesh'])\n"
                     "lo, hi = mesh.local_boxes()\ntree = jaxbvh.build(lo, hi, method='sweep')\n")
        exec(setup, scope)
        c0, w0 = _cpu(), time.perf_counter()
        exec(spec["call"], scope)
        first = (_cpu() - c0, time.perf_counter() - w0)
        cpu, wall = [], []
        for _ in range(args.repeat):
            c0, w0 = _cpu(), time.perf_counter()
            exec(spec["call"], scope)
            jax.effects_barrier()
            cpu.append(_cpu() - c0)
            wall.append(time.perf_counter() - w0)
        print(json.dumps({"entry": entry, "first_cpu": first[0], "first_wall": first[1],
                          "cpu_min": min(cpu), "cpu_median": statistics.median(cpu),
                          "wall_min": min(wall), "wall_median": statistics.median(wall),
                          "load": os.getloadavg()[0]}), flush=True)


if __name__ == "__main__":
    main()
