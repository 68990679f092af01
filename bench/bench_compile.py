"""Compile cost of every public entry point on its first call: cold, then from the cache.

For the issue "A first run that works: compile time cut". Every entry point (a builder, an
optimizer, a collapse, a ray trace, a two-level build, the README's example, a docs-style
session) runs twice, each time in a fresh Python process started without the test
suite's ``XLA_FLAGS`` (``XLA_FLAGS``, ``JAX_*`` and ``JAXBVH_*`` are removed from the
child's environment):

1. **cold**: jaxbvh's compilation cache (:mod:`jaxbvh.compile_cache`: JAX's persistent
   cache, every program written, and jaxbvh's program store beside it) in a new, empty
   folder (``JAXBVH_CACHE_DIR``), so every program is compiled (and written to the folder);
2. **warm**: a second fresh process with the same folder: every program is loaded from
   disk, not compiled (jaxbvh's programs also skip tracing and lowering: the store).

Measured in each child, for the call only (setup such as loading the mesh, a tree or rays
is done before and not counted; the inputs are prepared once by a separate process and
read from ``.npz`` files, so setup compiles nothing the call could reuse, except where
noted):

- ``cpu``: CPU seconds of the call, ``resource.getrusage(RUSAGE_SELF)`` user + sys (all
  threads, XLA's compile threads included), and ``wall`` seconds; also the CPU seconds of
  ``import jax`` and ``import jaxbvh`` and of the whole process;
- ``compiled``: programs compiled by XLA (``/jax/core/compile/backend_compile_duration``
  events not preceded, in the same thread, by a ``/jax/compilation_cache/cache_hits``
  event) and ``hits``: programs loaded from the persistent cache or, compiled code and
  all, from jaxbvh's program store (``jaxbvh.program_store.EXECUTABLE_LOAD_EVENT``);
- ``trace_s``, ``lower_s``, ``compile_s``: seconds of jaxpr tracing
  (``/jax/core/compile/jaxpr_trace_duration``), lowering jaxpr -> MLIR
  (``/jax/core/compile/jaxpr_to_mlir_module_duration``) and XLA compiling (backend compile
  events of the compiled programs). Tracing nests (an inner ``jit`` is traced inside its
  caller's trace, and both report), so ``trace_s`` is the length of the *union* of the
  reported intervals, not their sum (``trace_sum_s`` is the sum); ``retrieve_s``: the
  ``/jax/compilation_cache/cache_retrieval_time_sec`` sum (reading entries, hits and misses)
  plus the program store's load events;
- ``ops``: program size, the number of operations in the lowered StableHLO module of every
  program that went to the backend (compiled or loaded), counted by walking the MLIR module
  JAX hands to ``compile_or_get_cached`` (every op except ``builtin.module``,
  ``func.func`` and the ``func.return`` / ``stablehlo.return`` terminators; fused or
  inlined by XLA later, so it is the size of what XLA is given, before its
  optimizations). The walk's own CPU seconds are subtracted from ``cpu``; ``programs``
  lists each program's name, ops, compile seconds and whether it was a cache hit.

Entry points (names for ``--only``; ``@MESH`` is appended for ``--mesh`` inputs):
``build:<method>`` for every method of ``jaxbvh.builders.configs.ALL_BUILDERS``;
``optimize:<method>`` (``jaxbvh.optimize.optimize(tree, method)`` with its defaults, on a
sweep tree) and ``optimize:<method>:first`` (the same compiled programs, but one pass /
iteration / round: :data:`FIRST_PASS`); ``collapse:optimal|greedy|qbvh``;
``rays:trace`` / ``rays:measure`` (4,096 random closest-hit rays); ``twolevel:build``
(``jaxbvh.twolevel.build`` of ``scenes.by_material`` of the mesh, 8 objects); ``readme``
(the README's Python example, verbatim, as a whole script: its ``cpu`` includes its
10-second optimize budget) and ``session`` (a docs-style session: build, validate, sah,
optimize hc, collapse optimal, trace). For ``readme`` and ``session`` the number of
compiled programs is the number of distinct programs a typical script compiles.

Run (2 shared cores: the full run takes tens of minutes)::

    python bench/bench_compile.py                      # every entry on the bundled mesh
    python bench/bench_compile.py --quick              # build:sweep and optimize:hc:first
    python bench/bench_compile.py --only build:sbvh,readme
    python bench/bench_compile.py --mesh ../shared/data/meshes/fandisk.obj
    python bench/bench_compile.py --baseline bench/results/bench_compile_before.json
    python bench/bench_compile.py --repeat 3           # medians of 3 cold + warm pairs
    python bench/bench_compile.py --render bench/results/bench_compile.json --baseline OLD.json
    python bench/bench_compile.py --policy xla         # XLA's default options (jaxbvh.compile_policy)

Results: ``bench/results/bench_compile.json`` and ``.md`` (``--out`` to change; ``--quick``
and ``--only`` write ``bench_compile_partial.*`` unless ``--out`` is given).
``--baseline FILE.json`` puts that run's figures beside this run's in the markdown
("before → after"); ``--render`` only rewrites a results file's markdown and in the JSON (``baseline``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"

#: rays traced by the rays:* entries and the session (random rays filling the root box)
RAYS = 4096

#: options that make an optimizer stop after its first pass / iteration / round
#: (``optimize:<method>:first``); the rest of its Config is the default
FIRST_PASS = {
    "hc": {"max_passes": 1},
    "sa": {"steps": 1, "max_quench": 1},
    "reinsert": {"max_iterations": 1},
    "treelet": {"max_passes": 1},
    "pipeline": {"max_rounds": 1},
}

# The child: imports, configures the cache, listens, runs SETUP then CALL (Python source
# in the spec) and prints one JSON line. argv[1]: the spec as JSON.
_CHILD = r'''
import json, os, resource, sys, threading, time

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime

spec = json.loads(sys.argv[1])
c0 = cpu()
import jax
import jax.monitoring
c_jax = cpu() - c0
if spec["cache_dir"]:
    # jaxbvh's own cache in that folder (set at import jaxbvh: every program written, and
    # its program store on, which a cache configured in JAX directly would turn off)
    os.environ["JAXBVH_CACHE_DIR"] = spec["cache_dir"]

phase = ["import"]
local = threading.local()
events = []        # (phase, kind, start, end)
programs = []      # per backend event
retrieval = []     # (phase, seconds)
walk_cpu = [0.0]   # CPU seconds spent counting ops (subtracted from the call)
_SKIP = {"builtin.module", "func.func", "func.return", "stablehlo.return"}

def on_event(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        local.hit = True

def on_duration(event, duration, **kw):
    end = time.time()
    if event == "/jax/core/compile/jaxpr_trace_duration":
        events.append((phase[0], "trace", end - duration, end))
    elif event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
        events.append((phase[0], "lower", end - duration, end))
    elif event == "/jax/compilation_cache/cache_retrieval_time_sec":
        retrieval.append((phase[0], duration))
    elif event == "/jaxbvh/program_store/executable_load_sec":  # compiled code from jaxbvh's store
        retrieval.append((phase[0], duration))
        programs.append({"phase": phase[0], "name": "stored", "ops": None, "seconds": 0.0, "hit": True})
    elif event == "/jax/core/compile/backend_compile_duration":
        hit = getattr(local, "hit", False)
        local.hit = False
        module = getattr(local, "module", None) or {}
        local.module = None
        programs.append({"phase": phase[0], "name": kw.get("fun_name", module.get("name")),
                         "ops": module.get("ops"), "seconds": duration, "hit": hit})

jax.monitoring.register_event_listener(on_event)
jax.monitoring.register_event_duration_secs_listener(on_duration)

try:  # program size: count the ops of the module JAX is about to compile (or look up)
    from jax._src.interpreters import mlir as _mlir
    from jax._src.lib.mlir import ir as _ir
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
            name = _ir.StringAttr(module.operation.attributes["sym_name"]).value
            local.module = {"name": name, "ops": n[0]}
        except Exception:
            local.module = None
        walk_cpu[0] += cpu() - t
        return _dump(module, stage)

    _mlir.dump_module_to_file = _counting_dump
    counting = True
except Exception:
    counting = False

c1 = cpu()
import jaxbvh
c_jaxbvh = cpu() - c1

os.chdir(spec["workdir"])
scope = {"spec": spec, "jax": jax, "jaxbvh": jaxbvh}
phase[0] = "setup"
exec(compile(spec["setup"], "<setup>", "exec"), scope)
phase[0] = "call"
walk_cpu[0] = 0.0
c2, w2 = cpu(), time.perf_counter()
exec(compile(spec["call"], "<call>", "exec"), scope)
jax.effects_barrier()
wall = time.perf_counter() - w2
call_cpu = cpu() - c2 - walk_cpu[0]
# an optimize whose time budget ran out returns while its worker still compiles, and the
# process waits for that worker at exit: measured apart, as the "tail"
phase[0] = "tail"
walk_call = walk_cpu[0]
c3, w3 = cpu(), time.perf_counter()
compiling = getattr(getattr(jaxbvh.optimize, "driver", None), "compiling", None)
while compiling is not None and compiling():
    time.sleep(0.02)
tail_wall = time.perf_counter() - w3
tail_cpu = cpu() - c3 - (walk_cpu[0] - walk_call)
phase[0] = "done"

def union(intervals):
    total, end = 0.0, None
    for a, b in sorted(intervals):
        if end is None or a > end:
            total += b - a
            end = b
        elif b > end:
            total += b - end
            end = b
    return total

def stats(p):
    mine = [g for g in programs if g["phase"] == p]
    done = [g for g in mine if not g["hit"]]
    spans = {k: [(a, b) for q, kind, a, b in events if q == p and kind == k] for k in ("trace", "lower")}
    ops = [g["ops"] for g in mine if g["ops"] is not None]
    return {"compiled": len(done), "hits": len(mine) - len(done),
            "trace_s": union(spans["trace"]), "trace_sum_s": sum(b - a for a, b in spans["trace"]),
            "traces": len(spans["trace"]),
            "lower_s": sum(b - a for a, b in spans["lower"]), "lowers": len(spans["lower"]),
            "compile_s": sum(g["seconds"] for g in done),
            "hit_s": sum(g["seconds"] for g in mine if g["hit"]),
            "retrieve_s": sum(s for q, s in retrieval if q == p),
            "ops": sum(ops) if counting and len(ops) == len(mine) else None,
            "ops_compiled": sum(g["ops"] or 0 for g in done) if counting else None}

out = {"cpu": call_cpu, "wall": wall, "import_jax_cpu": c_jax, "import_jaxbvh_cpu": c_jaxbvh,
       "process_cpu": cpu() - walk_cpu[0], "setup": stats("setup"),
       "tail": dict(stats("tail"), cpu=tail_cpu, wall=tail_wall), **stats("call"),
       "programs": [{k: g[k] for k in ("name", "ops", "seconds", "hit")}
                    for g in programs if g["phase"] == "call"],
       "jax": jax.__version__}
print("BENCH_COMPILE_JSON " + json.dumps(out), flush=True)
'''

# setup / call source of each entry kind; {placeholders} filled by entries()
_LOAD_MESH = """
from jaxbvh.io import load_mesh
mesh = load_mesh(spec["mesh"])
lo, hi = mesh.local_boxes()
tri = mesh.local_triangles()
"""
_LOAD_TREE = """
import numpy as np
tree, frame = jaxbvh.load(spec["tree"])
"""
_LOAD_RAYS = _LOAD_TREE + _LOAD_MESH + """
with np.load(spec["rays"]) as r:
    origin, direction = r["origin"], r["direction"]
"""

_README_START = "## Python example"


def readme_example() -> str:
    """The README's Python example (the first ``python`` block after its heading), verbatim."""
    text = (ROOT / "README.md").read_text()
    block = text[text.index(_README_START):].split("```python\n", 1)[1].split("```", 1)[0]
    return block


def entries(mesh_path: str, tag: str) -> dict[str, dict]:
    """Every entry point: ``{name: {"group", "setup", "call"}}`` (Python source)."""
    from jaxbvh.builders.configs import ALL_BUILDERS, TRIANGLE_BUILDERS
    from jaxbvh.optimize import OPTIMIZERS

    out = {}
    for m in ALL_BUILDERS:
        extra = ", triangles=tri" if m in TRIANGLE_BUILDERS else ""
        out[f"build:{m}"] = {"group": "builders", "setup": _LOAD_MESH,
                             "call": f"jax.block_until_ready(jaxbvh.build(lo, hi, method={m!r}{extra}))"}
    for m in OPTIMIZERS:
        out[f"optimize:{m}"] = {"group": "optimizers", "setup": _LOAD_TREE,
                                "call": f"result = jaxbvh.optimize.optimize(tree, {m!r})"}
        opts = "".join(f", {k}={v!r}" for k, v in FIRST_PASS[m].items())
        out[f"optimize:{m}:first"] = {"group": "optimizers", "setup": _LOAD_TREE,
                                      "call": f"result = jaxbvh.optimize.optimize(tree, {m!r}{opts})"}
    for m in ("optimal", "greedy", "qbvh"):
        out[f"collapse:{m}"] = {"group": "collapse", "setup": _LOAD_TREE,
                                "call": f"jax.block_until_ready(jaxbvh.collapse.{m}(tree).tree)"}
    out["rays:trace"] = {"group": "rays", "setup": _LOAD_RAYS,
                         "call": "hits = jaxbvh.rays.trace(tree, tri, origin, direction)"}
    out["rays:measure"] = {"group": "rays", "setup": _LOAD_RAYS,
                           "call": "hits, summary = jaxbvh.rays.measure(tree, tri, origin, direction)"}
    out["twolevel:build"] = {"group": "two-level", "setup": _LOAD_MESH + """
from jaxbvh import scenes
v, f = mesh.objects[0]
scene = scenes.by_material(v, f)
""", "call": "tl = jax.block_until_ready(jaxbvh.twolevel.build(scene))"}
    if tag == "spot":  # the README's example reads the bundled mesh whatever --mesh says
        out["readme"] = {"group": "scripts", "setup": "", "call": readme_example()}
    out["session"] = {"group": "scripts", "setup": "", "call": """
import numpy as np
from jaxbvh import collapse, rays
from jaxbvh.io import load_mesh
mesh = load_mesh(spec["mesh"])
lo, hi = mesh.local_boxes()
tri = mesh.local_triangles()
tree = jaxbvh.build(lo, hi)
jaxbvh.validate(tree, lo, hi)
print("SAH", float(jaxbvh.sah(tree)))
result = jaxbvh.optimize.optimize(tree, "hc")
wide = collapse.optimal(result.tree)
with np.load(spec["rays"]) as r:
    origin, direction = r["origin"], r["direction"]
hits = rays.trace(result.tree, tri, origin, direction)
"""}
    for e in out.values():
        e["mesh_tag"] = tag
    return {(f"{name}@{tag}" if tag != "spot" else name): e for name, e in out.items()}


_PREPARE = r"""
import json, sys
import jax, numpy as np
import jaxbvh
from jaxbvh import rays
from jaxbvh.io import load_mesh
spec = json.loads(sys.argv[1])
mesh = load_mesh(spec["mesh"])
lo, hi = mesh.local_boxes()
tree = jaxbvh.build(lo, hi, method="sweep")
jaxbvh.save(spec["tree"], tree, frame=mesh.frame)
origin, direction = rays.make_rays(jax.random.key(0), "random", tree, mesh.local_triangles(), spec["rays_n"])
np.savez(spec["rays"], origin=np.asarray(origin), direction=np.asarray(direction))
print(json.dumps({"triangles": int(lo.shape[0])}))
"""


def child_env(extra_path: str) -> dict:
    """A plain environment: no XLA_FLAGS (the tests' unoptimized mode), no JAX / jaxbvh settings."""
    env = {k: v for k, v in os.environ.items()
           if k != "XLA_FLAGS" and not k.startswith(("JAX_", "JAXBVH_"))}
    env["PYTHONPATH"] = extra_path
    return env


def run_child(spec: dict, env: dict, timeout: float) -> dict:
    start = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(spec)], env=env, capture_output=True,
                         text=True, timeout=timeout)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("BENCH_COMPILE_JSON ")]
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"child failed (rc {out.returncode}): {out.stderr[-3000:]}")
    result = json.loads(lines[-1].split(" ", 1)[1])
    result["process_wall"] = time.perf_counter() - start
    return result


def median_run(runs: list[dict]) -> dict:
    """One child's figures from ``runs`` of the same child: the median of every number
    (nested dicts too); the first run's program list and other values."""
    def merge(values):
        first = values[0]
        if isinstance(first, dict):
            return {k: merge([v[k] for v in values]) for k in first}
        if isinstance(first, (int, float)) and not isinstance(first, bool) and all(
                isinstance(v, (int, float)) for v in values):
            m = statistics.median(values)
            return int(m) if isinstance(first, int) and m == int(m) else m
        return first
    return merge(runs)


def machine() -> str:
    """CPU model and core count."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores ({platform.machine()})"


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


# ---------------------------------------------------------------- markdown

#: (header, getter(row) -> number or None, format) of the markdown table's columns
COLUMNS = [
    ("cold CPU s", lambda r: r["cold"]["cpu"], "{:.2f}"),
    ("warm CPU s", lambda r: r["warm"]["cpu"], "{:.2f}"),
    ("cold wall s", lambda r: r["cold"]["wall"], "{:.2f}"),
    ("programs", None, None),
    ("warm compiled / hits", None, None),
    ("trace s", lambda r: r["cold"]["trace_s"], "{:.2f}"),
    ("lower s", lambda r: r["cold"]["lower_s"], "{:.2f}"),
    ("compile s", lambda r: r["cold"]["compile_s"], "{:.2f}"),
    ("warm trace+lower s", lambda r: r["warm"]["trace_s"] + r["warm"]["lower_s"], "{:.2f}"),
    ("warm retrieve s", lambda r: r["warm"]["retrieve_s"], "{:.2f}"),
    ("ops", lambda r: r["cold"]["ops"], "{:,d}"),
]


def _fmt(fmt, value):
    return "-" if value is None else fmt.format(value)


def _get(getter, row):
    try:
        return getter(row)
    except (KeyError, TypeError):
        return None


def _programs(row) -> str:
    """Programs compiled cold, and ``+ N again`` for those the cold process sent to XLA
    twice (the second time a persistent-cache hit: the in-memory jit cache missed)."""
    hits = row["cold"]["hits"]
    return f"{row['cold']['compiled']}" + (f" + {hits} again" if hits else "")


def markdown(results: dict, baseline: dict | None) -> str:
    before = {r["name"]: r for r in baseline["rows"]} if baseline else {}
    lines = ["# Compile cost of every entry point (issue: a first run that works)", "",
             f"`{results['command']}`; {results['date']}; machine: {results['machine']}; JAX {results['jax']} "
             f"on CPU; load average at start {results['load_start']}, at end {results['load_end']} "
             "(the cores are shared with other jobs: CPU seconds are the figure to read, wall seconds are "
             "noisy; each row's load average is in the JSON)"
             + (f"; every figure is the median of {results['repeat']} cold + warm pairs"
                if results.get("repeat", 1) > 1 else "; one cold + warm pair per entry") + ".", "",
             "Each entry runs in a fresh process with an empty persistent compilation cache (cold), then in "
             "a second fresh process that loads every program from that cache (warm); no XLA_FLAGS; jaxbvh's "
             f"compile policy `{results.get('policy', 'default')}` (jaxbvh.compile_policy). "
             "CPU s: `getrusage` user + sys of the call alone (setup excluded), all threads. programs: "
             "programs XLA compiled in the cold call (+ N again: sent to XLA a second time in that process "
             "and found in the persistent cache, i.e. the in-memory jit cache missed); warm compiled / hits: "
             "compiled again / loaded from the cache in the warm call. trace s: union of jaxpr tracing "
             "intervals; lower s: jaxpr -> MLIR; compile s: XLA backend compile (all cold); these three are "
             "wall seconds as JAX reports them (XLA compiles on several threads when cores are free, so "
             "compile s can be below the CPU s it costs). ops: StableHLO operations of the lowered programs "
             "the call sent to XLA (before XLA's optimizations). See the script's docstring.", ""]
    if baseline:
        lines += [f"Baseline (`before → after`): {baseline.get('date', '?')}, commit "
                  f"{baseline.get('commit', '?')}, load at start {baseline.get('load_start', '?')}.", ""]
    imports = [(r["cold"]["import_jax_cpu"], r["cold"]["import_jaxbvh_cpu"]) for r in results["rows"]]
    if imports:
        line = (f"Imports (CPU s, median of the {len(imports)} cold children): `import jax` "
                f"{statistics.median(i[0] for i in imports):.2f}, `import jaxbvh` "
                f"{statistics.median(i[1] for i in imports):.2f}")
        if baseline and baseline["rows"]:
            line += (f" (before: {statistics.median(r['cold']['import_jax_cpu'] for r in baseline['rows']):.2f}, "
                     f"{statistics.median(r['cold']['import_jaxbvh_cpu'] for r in baseline['rows']):.2f})")
        lines += [line + ".", ""]
    if results["rows"]:
        total = sum(r["cold"]["cpu"] for r in results["rows"])
        line = f"Sum over the {len(results['rows'])} entries of the cold call's CPU s: {total:.1f}"
        common = [r for r in results["rows"] if r["name"] in before]
        if common:
            line += (f"; over the {len(common)} entries also in the baseline: "
                     f"{sum(before[r['name']]['cold']['cpu'] for r in common):.1f} → "
                     f"{sum(r['cold']['cpu'] for r in common):.1f} (programs "
                     f"{sum(before[r['name']]['cold']['compiled'] for r in common)} → "
                     f"{sum(r['cold']['compiled'] for r in common)})")
        lines += [line + ".", ""]
    groups = list(dict.fromkeys(r["group"] for r in results["rows"]))
    for group in groups:
        lines += [f"## {group}", "", "| entry | " + " | ".join(c[0] for c in COLUMNS) + " | load |",
                  "|---|" + "---:|" * (len(COLUMNS) + 1)]
        for r in (r for r in results["rows"] if r["group"] == group):
            b = before.get(r["name"])
            cells = [r["name"]]
            for header, getter, fmt in COLUMNS:
                if header == "programs":  # + cache hits in the cold process: a program compiled twice
                    now, was = _programs(r), (_programs(b) if b else None)
                elif getter is None:  # warm compiled / hits
                    now = f"{r['warm']['compiled']} / {r['warm']['hits']}"
                    was = f"{b['warm']['compiled']} / {b['warm']['hits']}" if b else None
                else:
                    now = _fmt(fmt, _get(getter, r))
                    was = _fmt(fmt, _get(getter, b)) if b else None
                cells.append(f"{was} → {now}" if b else now)
            cells.append(r["load"].split()[0])  # 1-minute load average when the entry started
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    scripts = [r for r in results["rows"] if r["group"] == "scripts"]
    if scripts:
        lines += ["## Distinct programs a typical script compiles", ""]
        for r in scripts:
            names = sorted({p["name"] for p in r["cold"]["programs"] if not p["hit"]})
            b = before.get(r["name"])
            was = f" (before: {b['cold']['compiled']})" if b else ""
            tail = r["cold"].get("tail") or {}
            late = (f" (+ {tail['compiled']} more, {tail['cpu']:.1f} CPU s, compiled after the call returned, "
                    "by an optimize whose time budget ran out; the process waits for them at exit)"
                    if tail.get("compiled") else "")
            lines += [f"- `{r['name']}`: {r['cold']['compiled']} programs compiled{late}{was}, "
                      f"{len(names)} distinct names, process CPU {r['cold']['process_cpu']:.2f} s cold / "
                      f"{r['warm']['process_cpu']:.2f} s warm: " + ", ".join(f"`{n}`" for n in names)]
        lines.append("")
    # the same program (name and size) compiled by several entries is listed once
    seen = {}
    for r in results["rows"]:
        for p in r["cold"]["programs"]:
            if not p["hit"] and p["ops"]:
                seen.setdefault((p["name"], p["ops"]), {"seconds": [], "entries": []})
                seen[(p["name"], p["ops"])]["seconds"].append(p["seconds"])
                seen[(p["name"], p["ops"])]["entries"].append(r["name"])
    lines += ["## Largest programs (cold, by ops)", "",
              "| program | ops | compile s (median over entries) | entries |", "|---|---:|---:|---|"]
    for (name, ops), v in sorted(seen.items(), key=lambda kv: -kv[0][1])[:20]:
        lines.append(f"| `{name}` | {ops:,d} | {statistics.median(v['seconds']):.2f} | "
                     f"{', '.join(dict.fromkeys(v['entries']))} |")
    return "\n".join(lines) + "\n"


def write(out: Path, results: dict, baseline: dict | None) -> None:
    """Write ``out``.json and .md, each through a temporary file and a rename."""
    out.parent.mkdir(parents=True, exist_ok=True)
    for suffix, text in ((".json", json.dumps(results, indent=1)), (".md", markdown(results, baseline))):
        path = out.with_suffix(suffix)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, path)


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "?"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the fewest entries: build:sweep, optimize:hc:first")
    parser.add_argument("--only", default=None, help="comma-separated entry names (see the docstring)")
    parser.add_argument("--mesh", action="append", default=[],
                        help="also run every entry on this mesh (repeatable); names get @<file stem>")
    parser.add_argument("--baseline", default=None, help="a previous run's .json, shown beside this one")
    parser.add_argument("--out", default=None, help="results path without suffix (default: "
                        "bench/results/bench_compile, or bench_compile_partial for --quick / --only)")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per child process")
    parser.add_argument("--repeat", type=int, default=1,
                        help="cold + warm pairs per entry (each with a new cache); the tables show medians")
    parser.add_argument("--policy", default=None,
                        help="the children's JAXBVH_COMPILE_POLICY (jaxbvh.compile_policy; default: jaxbvh's default)")
    parser.add_argument("--list", action="store_true", help="print the entry names and exit")
    parser.add_argument("--render", default=None, metavar="FILE.json",
                        help="measure nothing: write FILE.md from FILE.json (with --baseline if given)")
    args = parser.parse_args(argv)
    baseline = json.loads(Path(args.baseline).read_text()) if args.baseline else None
    if args.render:
        path = Path(args.render)
        results = json.loads(path.read_text())
        if baseline:
            results["baseline"] = {"date": baseline.get("date"), "commit": baseline.get("commit"),
                                   "path": str(args.baseline)}
        write(path.with_suffix(""), results, baseline)
        print(f"wrote {path.with_suffix('.md')}")
        return

    from jaxbvh.io import bundled_mesh_path

    meshes = [("spot", str(bundled_mesh_path()))] + [(Path(m).stem, str(Path(m).resolve())) for m in args.mesh]
    table = {}
    for tag, path in meshes:
        for name, e in entries(path, tag).items():
            table[name] = dict(e, mesh=path)
    if args.list:
        print("\n".join(table))
        return
    if args.quick:
        names = ["build:sweep", "optimize:hc:first"]
    elif args.only:
        names = [n.strip() for n in args.only.split(",") if n.strip()]
    else:
        names = list(table)
    unknown = [n for n in names if n not in table]
    if unknown:
        parser.error(f"unknown entries {', '.join(unknown)}; --list shows them")
    out = Path(args.out) if args.out else RESULTS / ("bench_compile_partial" if (args.quick or args.only)
                                                     else "bench_compile")

    work = Path(tempfile.mkdtemp(prefix="jaxbvh-bench-compile-"))
    env = child_env(str(ROOT))
    if args.policy:
        env["JAXBVH_COMPILE_POLICY"] = args.policy
    prepared = {}
    for tag, path in meshes:
        # the sweep tree and the rays, for the entries that read them (a build reads neither)
        sources = [table[n]["setup"] + table[n]["call"] for n in names if table[n]["mesh"] == path]
        if not any('spec["tree"]' in src or 'spec["rays"]' in src for src in sources):
            continue
        spec = {"mesh": path, "tree": str(work / f"{tag}-sweep.npz"), "rays": str(work / f"{tag}-rays.npz"),
                "rays_n": RAYS}
        prep_env = dict(env, JAX_COMPILATION_CACHE_DIR=str(work / "prepare-cache"))
        done = subprocess.run([sys.executable, "-c", _PREPARE, json.dumps(spec)], env=prep_env,
                              capture_output=True, text=True, timeout=args.timeout)
        if done.returncode != 0:
            raise RuntimeError(f"preparing {path} failed: {done.stderr[-3000:]}")
        prepared[path] = dict(spec, triangles=json.loads(done.stdout.strip().splitlines()[-1])["triangles"])

    results = {"command": "python bench/bench_compile.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
               "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
               "commit": commit(), "machine": machine(), "python": platform.python_version(),
               "load_start": load(), "load_end": None, "repeat": args.repeat, "jax": None, "rays": RAYS,
               "policy": args.policy or "default",
               "first_pass": FIRST_PASS,
               "meshes": {tag: {"path": path, "triangles": prepared.get(path, {}).get("triangles")}
                          for tag, path in meshes},
               "rows": []}
    try:
        for name in names:
            e = table[name]
            load_before = load()
            colds, warms = [], []
            for k in range(args.repeat):  # each pair with its own new cache folder
                cache = work / name.replace(":", "_").replace("@", "_") / f"{k}" / "cache"
                workdir = cache.parent / "cwd"
                workdir.mkdir(parents=True)
                spec = {"setup": e["setup"], "call": e["call"], "cache_dir": str(cache),
                        "workdir": str(workdir), "mesh": e["mesh"], "tree": prepared.get(e["mesh"], {}).get("tree"),
                        "rays": prepared.get(e["mesh"], {}).get("rays")}
                colds.append(run_child(spec, env, args.timeout))
                warms.append(run_child(spec, env, args.timeout))
            cold, warm = median_run(colds), median_run(warms)
            results["jax"] = cold.pop("jax")
            warm.pop("jax")
            row = {"name": name, "group": e["group"], "mesh": e["mesh_tag"], "load": load_before,
                   "call": e["call"].strip(), "cold": cold, "warm": warm}
            if args.repeat > 1:
                row["cold_cpu_runs"] = [c["cpu"] for c in colds]
                row["warm_cpu_runs"] = [w["cpu"] for w in warms]
            results["rows"].append(row)
            print(f"{name:26s} cold {cold['cpu']:7.2f} CPU s ({cold['compiled']:3d} compiled, trace "
                  f"{cold['trace_s']:.2f} lower {cold['lower_s']:.2f} compile {cold['compile_s']:.2f}, "
                  f"{cold['ops'] or 0:,} ops)  warm {warm['cpu']:6.2f} CPU s ({warm['compiled']} compiled, "
                  f"{warm['hits']} hits)  load {load_before}", flush=True)
            results["load_end"] = load()
            write(out, results, baseline)  # after every entry: a partial run keeps what it measured
    finally:
        shutil.rmtree(work, ignore_errors=True)
    results["load_end"] = load()
    if baseline:
        results["baseline"] = {"date": baseline.get("date"), "commit": baseline.get("commit"),
                               "path": str(args.baseline)}
    write(out, results, baseline)
    print(f"wrote {out.with_suffix('.json')} and .md")


if __name__ == "__main__":
    main()
