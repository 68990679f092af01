"""Compile cost of one SBVH build (``jaxbvh.build(lo, hi, method="sbvh", triangles=tri)``).

    python bench/profile_sbvh_compile.py [--meshes spot,fandisk] [--out FILE.json]

For each mesh, three fresh Python processes (no ``XLA_FLAGS``, ``JAX_*`` or ``JAXBVH_*``
from the parent), all with ``JAXBVH_CACHE_DIR`` set to one new, empty folder:

1. **cold**: nothing in the persistent cache: every program is traced, lowered, compiled;
2. **warm**: the same folder: every program is traced and lowered again and loaded from disk;
3. a **run** figure: in the warm process, the same build called again (all compiled):
   CPU seconds of that second call (the build's own work).

Per process, for the build call only (the mesh is loaded before): ``cpu`` (process CPU
seconds, user + sys, all threads), ``compiled`` (backend compiles not answered by the
cache), ``hits`` (programs loaded from the cache), ``trace``, ``lower``, ``compile``
(sums of JAX's monitoring durations: jaxpr tracing, jaxpr -> MLIR, XLA backend compile;
trace durations nest, so ``trace`` can count an inner jit twice), ``retrieve``
(cache retrieval seconds). Wall-clock figures from JAX's events; ``cpu`` is the one to
compare on a shared machine (the load is printed with it).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MESHES = {"spot": None, "fandisk": "fandisk.obj", "rocker-arm": "rocker-arm.obj", "legocar": "legocar.obj",
          "bunny": "stanford-bunny.obj", "cow": "cow.obj", "teapot": "teapot.obj"}
MESH_DIR = ROOT.parent / "shared" / "data" / "meshes"

CHILD = r"""
import json, resource, sys, time
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
import jax, jax.monitoring
import numpy as np
import jaxbvh
from jaxbvh.io import bundled_mesh_path, load_mesh
path = sys.argv[1]
mesh = load_mesh(bundled_mesh_path() if path == "spot" else path)
lo, hi = mesh.local_boxes()
tri = mesh.local_triangles()
lo, hi, tri = (np.asarray(a, np.float32) for a in (lo, hi, tri))
sums = {"trace": 0.0, "lower": 0.0, "compile": 0.0, "retrieve": 0.0, "compiled": 0, "hits": 0}
names = {"/jax/core/compile/jaxpr_trace_duration": "trace",
         "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
         "/jax/core/compile/backend_compile_duration": "compile",
         "/jax/compilation_cache/cache_retrieval_time_sec": "retrieve"}
def on_duration(event, duration, **kw):
    if event in names:
        sums[names[event]] += duration
    if event == "/jax/core/compile/backend_compile_duration":
        sums["compiled"] += 1
def on_event(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        sums["hits"] += 1
jax.monitoring.register_event_duration_secs_listener(on_duration)
jax.monitoring.register_event_listener(on_event)
c0, w0 = cpu(), time.perf_counter()
out = jaxbvh.build(lo, hi, method="sbvh", triangles=tri)
jax.block_until_ready(out)
c1, w1 = cpu(), time.perf_counter()
result = dict(sums, cpu=c1 - c0, wall=w1 - w0, n=int(tri.shape[0]))
# backend compile events are also sent for cache hits: count only the misses
result["compiled"] -= result["hits"]
c2 = cpu()
jax.block_until_ready(jaxbvh.build(lo, hi, method="sbvh", triangles=tri))
result["run"] = cpu() - c2
print("RESULT " + json.dumps(result))
"""


def child(path: str, cache: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XLA_", "JAX_", "JAXBVH_"))}
    env["JAXBVH_CACHE_DIR"] = cache
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([sys.executable, "-c", CHILD, path], env=env, capture_output=True, text=True, timeout=1800)
    lines = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
    if proc.returncode or not lines:
        raise RuntimeError(f"child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", default="spot,fandisk")
    parser.add_argument("--out", default=None, help="also write the rows as JSON here")
    args = parser.parse_args(argv)
    rows = []
    header = (f"{'mesh':<11}{'tris':>7} {'pass':<5}{'progs':>6}{'hits':>5}{'trace s':>9}{'lower s':>9}"
              f"{'compile s':>10}{'retr s':>8}{'CPU s':>8}{'run CPU s':>10}  load")
    print(header, flush=True)
    for name in args.meshes.split(","):
        path = "spot" if MESHES.get(name) is None and name == "spot" else str(MESH_DIR / (MESHES.get(name) or name))
        with tempfile.TemporaryDirectory() as cache:
            for kind in ("cold", "warm"):
                r = child(path, cache)
                load = os.getloadavg()[0]
                r.update(mesh=name, kind=kind, load=load)
                rows.append(r)
                print(f"{name:<11}{r['n']:>7} {kind:<5}{r['compiled']:>6}{r['hits']:>5}{r['trace']:>9.2f}"
                      f"{r['lower']:>9.2f}{r['compile']:>10.2f}{r['retrieve']:>8.2f}{r['cpu']:>8.2f}"
                      f"{r['run']:>10.3f}  {load:.1f}", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
