"""Compile cost of each builder's first call, program by program, beside its run time.

For the issue "cut the cold compile cost of the top-down builders". For every builder
(``--methods``, default sweep, binned, median, ploc, lbvh) on the bundled spot mesh
(``--mesh`` for another), three fresh Python processes are started, each without the
test suite's ``XLA_FLAGS`` (``XLA_FLAGS``, ``JAX_*`` and ``JAXBVH_*`` are removed, then set
as below):

1. **cold**: ``JAXBVH_CACHE=off`` (no persistent cache: every program is compiled). The
   child loads the mesh, then measures the first ``jaxbvh.build(lo, hi, method=m,
   triangles=tri)``: CPU seconds (``getrusage`` user + sys, every thread, XLA's compile
   threads included) and wall seconds; the programs that went to XLA, each with its
   backend compile seconds (``/jax/core/compile/backend_compile_duration``, wall), and the
   summed ``jaxpr_trace_duration`` and ``jaxpr_to_mlir_module_duration`` (wall). Then it
   calls the same build ``--repeat`` more times and keeps the least wall and CPU seconds:
   the **run** time, compiled code only.
2. **fill**: ``JAXBVH_CACHE_DIR`` a new empty folder: the first call writes every program.
3. **warm**: a second process on that folder: the first call's CPU and wall seconds,
   traced and lowered again, every program read from disk, none compiled (``hits``).

``--runtime-mesh PATH`` adds the run time (least of ``--repeat`` calls after a first) of
each builder on a second, bigger mesh, in one more child.

Run (2 shared cores; say the load, ``uptime``, with the numbers)::

    python bench/profile_build_compile.py
    python bench/profile_build_compile.py --methods sweep,binned --runtime-mesh ../shared/data/meshes/stanford-bunny.obj
    PYTHONPATH=/path/to/other/checkout python bench/profile_build_compile.py --label before

Prints one Markdown table (and ``--json FILE`` writes the figures); the results with
before/after figures are kept in ``bench/results/profile_build_compile.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

METHODS = ("sweep", "binned", "median", "ploc", "lbvh")

# The child: argv[1] a JSON spec {mesh, method, repeat, runs_only}; prints one JSON line.
_CHILD = r'''
import json, resource, sys, time
spec = json.loads(sys.argv[1])

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime

import jax, jax.monitoring
sums, programs, hits = {}, [], [0]

def on_duration(event, duration, **kw):
    sums[event] = sums.get(event, 0.0) + duration
    if event == "/jax/core/compile/backend_compile_duration":
        programs.append((kw.get("fun_name"), round(duration, 3)))

def on_event(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        hits[0] += 1

jax.monitoring.register_event_duration_secs_listener(on_duration)
jax.monitoring.register_event_listener(on_event)
import jaxbvh
from jaxbvh.io import bundled_mesh_path, load_mesh
mesh = load_mesh(spec["mesh"] or bundled_mesh_path())
lo, hi = mesh.local_boxes()
tri = mesh.local_triangles()

def call():
    c, w = cpu(), time.perf_counter()
    jax.block_until_ready(jaxbvh.build(lo, hi, method=spec["method"], triangles=tri))
    return time.perf_counter() - w, cpu() - c

out = {"n": int(lo.shape[0])}
if not spec["runs_only"]:
    sums.clear(); programs.clear(); hits[0] = 0
    out["wall"], out["cpu"] = call()
    out["trace_s"] = sums.get("/jax/core/compile/jaxpr_trace_duration", 0.0)
    out["lower_s"] = sums.get("/jax/core/compile/jaxpr_to_mlir_module_duration", 0.0)
    out["backend_s"] = sums.get("/jax/core/compile/backend_compile_duration", 0.0)
    out["programs"] = sorted(programs, key=lambda p: -p[1])
    out["hits"] = hits[0]
runs = [call() for _ in range(spec["repeat"] + (1 if spec["runs_only"] else 0))][1 if spec["runs_only"] else 0:]
if runs:
    out["run_wall"] = min(r[0] for r in runs)
    out["run_cpu"] = min(r[1] for r in runs)
print("RESULT " + json.dumps(out))
'''


def child(method: str, *, mesh: str | None, repeat: int, env_extra: dict, runs_only: bool = False) -> dict:
    """One fresh process measuring ``method``; its JSON result."""
    env = {k: v for k, v in os.environ.items()
           if k != "XLA_FLAGS" and not k.startswith(("JAX_", "JAXBVH_"))}
    env.update(env_extra)
    spec = {"mesh": mesh, "method": method, "repeat": repeat, "runs_only": runs_only}
    done = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(spec)], env=env, capture_output=True,
                          text=True, timeout=1800)
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if done.returncode or not lines:
        raise RuntimeError(f"{method}: child failed\n{done.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def profile(method: str, *, mesh: str | None, runtime_mesh: str | None, repeat: int) -> dict:
    """Cold, warm and run figures of one builder (module docstring)."""
    cold = child(method, mesh=mesh, repeat=repeat, env_extra={"JAXBVH_CACHE": "off"})
    with tempfile.TemporaryDirectory(prefix="jaxbvh-profile-cache-") as folder:
        child(method, mesh=mesh, repeat=0, env_extra={"JAXBVH_CACHE_DIR": folder})
        warm = child(method, mesh=mesh, repeat=0, env_extra={"JAXBVH_CACHE_DIR": folder})
    row = {"method": method, "cold": cold, "warm": warm}
    if runtime_mesh:
        row["big"] = child(method, mesh=runtime_mesh, repeat=repeat, env_extra={"JAXBVH_CACHE": "off"},
                           runs_only=True)
    return row


def table(rows: list[dict]) -> str:
    """The Markdown table of :func:`profile` rows."""
    head = ("| builder | programs (backend s, largest first) | trace s | lower s | backend s "
            "| cold CPU s | cold wall s | warm CPU s (hits) | run CPU / wall s | big run CPU / wall s |")
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        c, w = r["cold"], r["warm"]
        progs = ", ".join(f"{name} {sec:.2f}" for name, sec in c["programs"][:3])
        if len(c["programs"]) > 3:
            progs += f", +{len(c['programs']) - 3} more"
        big = f"{r['big']['run_cpu']:.3f} / {r['big']['run_wall']:.3f} (n={r['big']['n']})" if "big" in r else "-"
        lines.append(f"| {r['method']} | {progs} | {c['trace_s']:.2f} | {c['lower_s']:.2f} | {c['backend_s']:.2f} "
                     f"| {c['cpu']:.2f} | {c['wall']:.2f} | {w['cpu']:.2f} ({w['hits']}) "
                     f"| {c['run_cpu']:.3f} / {c['run_wall']:.3f} | {big} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated builders")
    parser.add_argument("--mesh", default=None, help="mesh of the compile figures (default: bundled spot)")
    parser.add_argument("--runtime-mesh", default=None, help="a bigger mesh for run time only")
    parser.add_argument("--repeat", type=int, default=3, help="calls after the first; the least is kept")
    parser.add_argument("--json", default=None, help="write the figures here")
    args = parser.parse_args(argv)
    load = os.getloadavg()
    rows = []
    for method in args.methods.split(","):
        rows.append(profile(method, mesh=args.mesh, runtime_mesh=args.runtime_mesh, repeat=args.repeat))
        print(f"{method} done", file=sys.stderr, flush=True)
    after = os.getloadavg()
    print(table(rows))
    print(f"\nload average (1 min) {load[0]:.2f} at start, {after[0]:.2f} at end")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "load": [load[0], after[0]]}, f, indent=1)


if __name__ == "__main__":
    main()
