"""Where the optimizers' cold compile goes: programs, trace / lower / XLA seconds, CPU seconds.

For the issue "optimizers: cut the cold compile cost" (target: each optimizer's first
``jaxbvh.optimize.optimize(tree, method)`` at most 5 CPU seconds cold on the bundled spot
mesh, a warm run at most 1 s). For every method of :data:`jaxbvh.optimize.OPTIMIZERS`
one fresh child process (no persistent compile cache: ``JAXBVH_CACHE=off``; no
``XLA_FLAGS``, no other ``JAX_*`` / ``JAXBVH_*`` settings) builds a sweep tree of the mesh (its programs are compiled during
the setup and not counted), then runs ``optimize(tree, method)`` with the method's
defaults twice:

- ``cold``: CPU seconds (``getrusage`` user + sys, every thread) and wall seconds of the
  first call, which compiles every program of the optimizer;
- ``warm``: the same call again in the same process (every program compiled already);
- ``programs``: each program XLA compiled during the first call, by name
  (``fun_name`` of the ``/jax/core/compile/backend_compile_duration`` event), its size
  (operations in the StableHLO module XLA is given) and its XLA seconds;
- ``trace_s`` / ``lower_s`` / ``backend_s``: wall seconds of jaxpr tracing (the union of
  the nested intervals), lowering to MLIR and XLA compiling, during the first call.

Run::

    python bench/profile_optimize_compile.py                 # every method, spot mesh
    python bench/profile_optimize_compile.py --only hc,sa
    python bench/profile_optimize_compile.py --mesh ../shared/data/meshes/fandisk.obj

Results (the table printed; before/after kept in bench/results/profile_optimize_compile.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r'''
import json, resource, sys, threading, time

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime

spec = json.loads(sys.argv[1])
import jax, jax.monitoring
from jax._src.interpreters import mlir as _mlir
from jax._src.lib.mlir import ir as _ir

local = threading.local()
phase = ["setup"]
spans, programs = [], []
walk = [0.0]
_SKIP = {"builtin.module", "func.func", "func.return", "stablehlo.return"}

def on_duration(event, duration, **kw):
    end = time.time()
    if phase[0] != "cold":
        return
    if event == "/jax/core/compile/jaxpr_trace_duration":
        spans.append(("trace", end - duration, end))
    elif event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
        spans.append(("lower", end - duration, end))
    elif event == "/jax/core/compile/backend_compile_duration":
        module = getattr(local, "module", None) or {}
        local.module = None
        programs.append({"name": kw.get("fun_name", module.get("name")), "ops": module.get("ops"),
                         "seconds": duration})

jax.monitoring.register_event_duration_secs_listener(on_duration)
_dump = _mlir.dump_module_to_file

def _counting_dump(module, stage):
    t = cpu()
    n = [0]
    def visit(op):
        if op.name not in _SKIP:
            n[0] += 1
        return _ir.WalkResult.ADVANCE
    try:
        module.operation.walk(visit)
        local.module = {"name": _ir.StringAttr(module.operation.attributes["sym_name"]).value, "ops": n[0]}
    except Exception:
        local.module = None
    walk[0] += cpu() - t
    return _dump(module, stage)

_mlir.dump_module_to_file = _counting_dump

import jaxbvh
from jaxbvh.io import load_mesh
mesh = load_mesh(spec["mesh"])
lo, hi = mesh.local_boxes()
tree = jaxbvh.build(lo, hi, method="sweep")
jax.block_until_ready(tree)

def union(intervals):
    total, end = 0.0, None
    for a, b in sorted(intervals):
        if end is None or a > end:
            total, end = total + b - a, b
        elif b > end:
            total, end = total + b - end, b
    return total

phase[0] = "cold"
walk[0] = 0.0
c, w = cpu(), time.perf_counter()
first = jaxbvh.optimize.optimize(tree, spec["method"])
cold_wall, cold_cpu = time.perf_counter() - w, cpu() - c - walk[0]
phase[0] = "warm"
c, w = cpu(), time.perf_counter()
second = jaxbvh.optimize.optimize(tree, spec["method"])
warm_wall, warm_cpu = time.perf_counter() - w, cpu() - c
print("PROFILE_JSON " + json.dumps({
    "cold_cpu": cold_cpu, "cold_wall": cold_wall, "warm_cpu": warm_cpu, "warm_wall": warm_wall,
    "trace_s": union([(a, b) for k, a, b in spans if k == "trace"]),
    "lower_s": sum(b - a for k, a, b in spans if k == "lower"),
    "backend_s": sum(p["seconds"] for p in programs), "programs": programs,
    "sah": float(first.sah), "sah_start": float(first.sah_start), "steps": int(first.steps),
    "same_warm": float(second.sah) == float(first.sah)}), flush=True)
'''


def profile(method: str, mesh: str, timeout: float) -> dict:
    """One fresh child's figures for ``method`` (module docstring)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS" and not k.startswith(("JAX_", "JAXBVH_"))}
    env["JAXBVH_CACHE"] = "off"  # jaxbvh turns JAX's persistent cache on at import: cold means none
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    out = subprocess.run([sys.executable, "-c", _CHILD, json.dumps({"method": method, "mesh": mesh})],
                         env=env, capture_output=True, text=True, timeout=timeout)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("PROFILE_JSON ")]
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"{method}: child failed (rc {out.returncode}): {out.stderr[-3000:]}")
    return json.loads(lines[-1].split(" ", 1)[1])


def main(argv=None) -> None:
    from jaxbvh.io import bundled_mesh_path
    from jaxbvh.optimize import OPTIMIZERS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="comma-separated methods (default: all)")
    parser.add_argument("--mesh", default=None, help="mesh file (default: the bundled spot)")
    parser.add_argument("--programs", action="store_true", help="list every compiled program")
    parser.add_argument("--timeout", type=float, default=900.0)
    args = parser.parse_args(argv)
    methods = [m for m in args.only.split(",") if m] or list(OPTIMIZERS)
    mesh = args.mesh or str(bundled_mesh_path())
    load = os.getloadavg()
    print(f"mesh {Path(mesh).name}; load before {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(f"{'method':9} {'cold cpu':>8} {'wall':>6} {'progs':>5} {'ops':>7} {'trace':>6} {'lower':>6} "
          f"{'xla':>6} {'warm cpu':>8} {'wall':>6} {'steps':>5}  sah")
    for m in methods:
        r = profile(m, mesh, args.timeout)
        ops = sum(p["ops"] or 0 for p in r["programs"])
        print(f"{m:9} {r['cold_cpu']:8.2f} {r['cold_wall']:6.2f} {len(r['programs']):5d} {ops:7d} "
              f"{r['trace_s']:6.2f} {r['lower_s']:6.2f} {r['backend_s']:6.2f} {r['warm_cpu']:8.2f} "
              f"{r['warm_wall']:6.2f} {r['steps']:5d}  {r['sah']:.6g}", flush=True)
        if args.programs:
            for p in sorted(r["programs"], key=lambda p: -p["seconds"]):
                print(f"    {p['seconds']:6.2f} s {p['ops'] or 0:6d} ops  {p['name']}")
    load = os.getloadavg()
    print(f"load after {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    main()
