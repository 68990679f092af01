"""Second-run cost of the command line tool: what a CLI run spends beyond its warm work.

For each command (on the bundled mesh, or a tree built from it) this runs, each in a
fresh process sharing one new compilation-cache folder:

1. the command once (cold: it compiles and fills the cache),
2. the command again (the "second run" a user sees), counting the programs JAX compiled
   rather than loaded from the persistent cache (``/jax/core/compile/backend_compile_duration``
   events, which JAX also records for cache hits, minus ``/jax/compilation_cache/cache_hits``
   events; 0 means every program came from the cache),

and, in one process, the command twice through ``jaxbvh.cli``: the second of those
is the *warm* time (everything compiled and in memory). ``overhead = second run -
warm``: Python and JAX start-up plus loading compiled programs from the cache (and any
compiling the cache missed). Target (issue "Every command fast on its second run"):
under 1 s for build, optimize hc, optimize sa and trace.

Run: ``python bench/bench_cli.py [--repeats 3]``; results in ``bench/results/cli.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"

# runs a CLI command in this process and prints one JSON line with the backend compiles
# JAX reported and the wall time of cli.main
_PROBE = r"""
import json, sys, time
t0 = time.perf_counter()
import jax.monitoring
hits = []
compiles = []
def listen(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        hits.append(1)
def listen_duration(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":  # cache hits included
        compiles.append(duration)
jax.monitoring.register_event_listener(listen)
jax.monitoring.register_event_duration_secs_listener(listen_duration)
from jaxbvh import cli
import contextlib, io
with contextlib.redirect_stdout(io.StringIO()):
    status = cli.main(sys.argv[1:])
print(json.dumps({"status": status, "compiles": len(compiles) - len(hits), "hits": len(hits),
                  "seconds": time.perf_counter() - t0}))
"""

_WARM = r"""
import json, sys, time, contextlib, io
from jaxbvh import cli
times = []
for _ in range(2):
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        assert cli.main(sys.argv[1:]) == 0
    times.append(time.perf_counter() - t0)
print(json.dumps({"first": times[0], "warm": times[1]}))
"""


def probe(argv, env) -> dict:
    """Run ``jaxbvh ARGV`` in a fresh process; wall time and backend compiles."""
    start = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", _PROBE, *argv], env=env, capture_output=True,
                         text=True, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["wall"] = time.perf_counter() - start
    if result["status"] != 0:
        raise RuntimeError(f"jaxbvh {' '.join(argv)} failed: {out.stderr[-2000:]}")
    return result


def warm(argv, env) -> dict:
    out = subprocess.run([sys.executable, "-c", _WARM, *argv], env=env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="second runs per command (median)")
    parser.add_argument("--out", default=str(RESULTS / "cli"), help="results path without suffix")
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="jaxbvh-bench-cli-"))
    env = dict(os.environ, JAXBVH_CACHE_DIR=str(work / "cache"), PYTHONPATH=str(ROOT))
    tree = work / "spot.npz"
    subprocess.run([sys.executable, "-m", "jaxbvh.cli", "build", "-o", str(tree), "--json"],
                   env=dict(env, JAXBVH_CACHE_DIR=str(work / "scratch-cache")), check=True,
                   capture_output=True)
    from jaxbvh.io import bundled_mesh_path

    mesh = str(bundled_mesh_path())
    cases = {
        "build": ["build", "--json"],
        "optimize hc": ["optimize", str(tree), "--method", "hc", "--json"],
        "optimize sa (N=100, 2 chains)": ["optimize", str(tree), "--method", "sa", "--steps", "100",
                                          "--chains", "2", "--json"],
        "trace (10k rays)": ["trace", str(tree), mesh, "--rays", "10000", "--json"],
    }
    rows = []
    for name, argv in cases.items():
        cold = probe(argv, env)
        seconds = [probe(argv, env) for _ in range(args.repeats)]
        w = warm(argv, env)
        second = statistics.median(s["wall"] for s in seconds)
        row = {"command": name, "argv": argv, "cold": cold["wall"], "cold_compiles": cold["compiles"],
               "second": second, "second_compiles": max(s["compiles"] for s in seconds),
               "second_cache_hits": min(s["hits"] for s in seconds),
               "warm": w["warm"], "overhead": second - w["warm"]}
        rows.append(row)
        print(f"{name:32s} cold {row['cold']:6.2f} s ({row['cold_compiles']} compiles)  second "
              f"{second:6.2f} s ({row['second_compiles']} compiles)  warm {row['warm']:6.2f} s  "
              f"overhead {row['overhead']:5.2f} s", flush=True)

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"machine": f"{os.cpu_count()} cores, {sys.platform}", "python": sys.version.split()[0],
            "repeats": args.repeats}
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = ["| command | cold run (s) | compiles | second run (s) | compiles | warm, in-process (s) | "
             "overhead (s) |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['command']} | {r['cold']:.2f} | {r['cold_compiles']} | {r['second']:.2f} | "
                     f"{r['second_compiles']} | {r['warm']:.2f} | {r['overhead']:.2f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
