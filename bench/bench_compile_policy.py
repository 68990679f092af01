"""XLA compiler options on CPU: what each costs to compile and what the compiled code then runs at.

For the compile policy of issue 38 (:mod:`jaxbvh.compile_policy`). Each *entry* (a
program family: the builders, SBVH, each optimizer, collapse, the two-level build, a ray
trace) runs under each *config* (a set of XLA options), each pair in a fresh Python
process with no persistent cache (``JAXBVH_CACHE=off``: nothing is loaded from disk, so
the first call compiles everything), and measures:

- ``cold_cpu``: CPU seconds (``getrusage`` user + sys, all threads) of the first call:
  tracing, lowering, compiling and one run. ``compile_s``: XLA backend compile seconds
  JAX reports (``/jax/core/compile/backend_compile_duration``, wall); ``compile_cpu``:
  ``cold_cpu`` minus the best hot run's CPU, i.e. the first call's cost beyond running;
- ``run_cpu`` / ``run_wall``: the fastest of :data:`HOT_RUNS` further identical calls
  (compiled programs held in memory): the speed of the compiled code, and ``work`` /
  ``unit``: what one call does (optimizer steps, rays), so ``per_s`` = work / run_cpu.

Configs are given as ``XLA_FLAGS`` (the same DebugOptions fields that ``jax.jit(...,
compiler_options=...)`` sets per program) with ``JAXBVH_COMPILE_POLICY=xla`` so that
jaxbvh adds no options of its own, except the config ``policy``: no ``XLA_FLAGS`` and
jaxbvh's own per-program policy. The inputs (a sweep tree, rays) are made once per mesh
by a separate process. Entries and configs alternate (for each entry, every config in
turn) so that a change of load hits every config alike.

Run (2 shared cores: a full run takes most of an hour)::

    python bench/bench_compile_policy.py
    python bench/bench_compile_policy.py --only build:sweep,optimize:hc --configs xla,both
    python bench/bench_compile_policy.py --mesh ../shared/data/meshes/rocker-arm.obj --only optimize:hc
    python bench/bench_compile_policy.py --append --only build:sbvh --configs policy   # add rows

Results: ``bench/results/bench_compile_policy.json`` and ``.md`` (``--out`` to change).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_compile import _LOAD_MESH, _LOAD_RAYS, _LOAD_TREE, _PREPARE, child_env, commit, load, machine  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"

#: hot calls after the first; the fastest one is the run speed
HOT_RUNS = 3
#: rays per trace call (the trace batches 16,384 rays per program call)
RAYS = 65536

#: name -> XLA_FLAGS (None: jaxbvh's own policy, no XLA_FLAGS)
CONFIGS = {
    "xla": "",
    "nofusion": "--xla_cpu_use_fusion_emitters=false",
    "O0": "--xla_backend_optimization_level=0",
    "both": "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false",
    "O1": "--xla_backend_optimization_level=1",
    "O1+nofusion": "--xla_backend_optimization_level=1 --xla_cpu_use_fusion_emitters=false",
    "O2+nofusion": "--xla_backend_optimization_level=2 --xla_cpu_use_fusion_emitters=false",
    "cheap-llvm": "--xla_llvm_disable_expensive_passes=true",
    "cheap-llvm+nofusion": "--xla_llvm_disable_expensive_passes=true --xla_cpu_use_fusion_emitters=false",
    "policy": None,
}
DEFAULT_CONFIGS = ("xla", "nofusion", "O0", "both", "policy")

#: name -> (setup, call, work expression, unit); the call is run 1 + HOT_RUNS times
ENTRIES = {
    "build:sweep": (_LOAD_MESH, "out = jax.block_until_ready(jaxbvh.build(lo, hi, method='sweep'))", "1", "build"),
    "build:ploc": (_LOAD_MESH, "out = jax.block_until_ready(jaxbvh.build(lo, hi, method='ploc'))", "1", "build"),
    "build:sbvh": (_LOAD_MESH, "out = jax.block_until_ready(jaxbvh.build(lo, hi, method='sbvh', triangles=tri))",
                   "1", "build"),
    "optimize:hc": (_LOAD_TREE, "out = jaxbvh.optimize.optimize(tree, 'hc', max_passes=8)", "int(out.steps)", "pass"),
    "optimize:sa": (_LOAD_TREE, "out = jaxbvh.optimize.optimize(tree, 'sa', steps=16, max_quench=1)",
                    "int(out.steps)", "pass"),
    "optimize:reinsert": (_LOAD_TREE, "out = jaxbvh.optimize.optimize(tree, 'reinsert', max_iterations=4)",
                          "int(out.steps)", "iteration"),
    "optimize:pipeline": (_LOAD_TREE, "out = jaxbvh.optimize.optimize(tree, 'pipeline', max_rounds=2)",
                          "int(out.steps)", "step"),
    "collapse:optimal": (_LOAD_TREE, "out = jax.block_until_ready(jaxbvh.collapse.optimal(tree).tree)", "1",
                         "collapse"),
    "twolevel:build": (_LOAD_MESH + """
from jaxbvh import scenes
v, f = mesh.objects[0]
scene = scenes.by_material(v, f)
""", "out = jax.block_until_ready(jaxbvh.twolevel.build(scene))", "1", "build"),
    "rays:trace": (_LOAD_RAYS, "out = jaxbvh.rays.trace(tree, tri, origin, direction)", "origin.shape[0]", "ray"),
}

_CHILD = r'''
import json, resource, sys, time
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
spec = json.loads(sys.argv[1])
import jax, jax.monitoring
compile_s = [0.0]
def on_duration(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":
        compile_s[0] += duration
jax.monitoring.register_event_duration_secs_listener(on_duration)
import jaxbvh
scope = {"spec": spec, "jax": jax, "jaxbvh": jaxbvh}
exec(compile(spec["setup"], "<setup>", "exec"), scope)
call = compile(spec["call"], "<call>", "exec")
compile_s[0] = 0.0
c, w = cpu(), time.perf_counter()
exec(call, scope)
cold = {"cold_cpu": cpu() - c, "cold_wall": time.perf_counter() - w, "compile_s": compile_s[0]}
work = eval(spec["work"], scope)
runs = []
for _ in range(spec["hot"]):
    c, w = cpu(), time.perf_counter()
    exec(call, scope)
    runs.append((cpu() - c, time.perf_counter() - w))
assert eval(spec["work"], scope) == work
best = min(runs)
print("POLICY_JSON " + json.dumps(dict(cold, run_cpu=best[0], run_wall=best[1], hot_compile_s=compile_s[0] - cold["compile_s"],
                                      work=work, runs=runs, jax=jax.__version__)), flush=True)
'''


def env_for(config: str, base: dict) -> dict:
    env = dict(base, JAXBVH_CACHE="off")
    flags = CONFIGS[config]
    if flags is not None:
        env["JAXBVH_COMPILE_POLICY"] = "xla"  # the flags alone: jaxbvh adds no options
        if flags:
            env["XLA_FLAGS"] = flags
    return env


def markdown(results: dict) -> str:
    configs = results["configs"]
    lines = ["# XLA options on CPU: compile cost and run speed per program family", "",
             f"`{results['command']}`; {results['date']}; commit {results['commit']}; {results['machine']}; "
             f"JAX {results['jax']}; load average at start {results['load_start']}, at end {results['load_end']} "
             "(2 shared cores: read CPU seconds; each row's 1-minute load is in the last column).", "",
             "Each cell: one fresh process, no persistent cache. **first** = CPU s of the first call (trace, lower, "
             "XLA compile, one run); **run** = CPU s of the fastest of "
             f"{HOT_RUNS} further identical calls (the compiled code's speed), with the work of one call. "
             "Configs: " + "; ".join(f"`{c}` = " + (f"`{CONFIGS[c]}`" if CONFIGS[c] else
                                                     ("XLA defaults" if CONFIGS[c] == "" else "jaxbvh's policy"))
                                     for c in configs) + ".", ""]
    if results.get("notes"):
        lines += ["## What the numbers say", ""] + [f"- {note}" for note in results["notes"]] + [""]
    header = "| entry (work per call) | " + " | ".join(f"{c} first / run" for c in configs) + " | load |"
    lines += ["## CPU seconds: first call / one hot call", "", header, "|---|" + "---:|" * (len(configs) + 1)]
    for row in results["rows"]:
        cells = [f"{row['name']}@{row['mesh']} ({row['work']} {row['unit']})"]
        for c in configs:
            r = row["configs"].get(c)
            cells.append("-" if r is None else f"{r['cold_cpu']:.2f} / {r['run_cpu']:.3f}")
        cells.append(row["load"].split()[0])
        lines.append("| " + " | ".join(cells) + " |")
    base = configs[0]
    lines += ["", f"## Relative to `{base}`: first-call CPU ×, run CPU ×", "",
              "| entry | " + " | ".join(configs[1:]) + " |", "|---|" + "---:|" * (len(configs) - 1)]
    for row in results["rows"]:
        b = row["configs"].get(base)
        cells = [f"{row['name']}@{row['mesh']}"]
        for c in configs[1:]:
            r = row["configs"].get(c)
            cells.append("-" if r is None or b is None else
                         f"{r['cold_cpu'] / b['cold_cpu']:.2f} / {r['run_cpu'] / max(b['run_cpu'], 1e-9):.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## XLA backend compile seconds (wall, as JAX reports them)", "",
              "| entry | " + " | ".join(configs) + " |", "|---|" + "---:|" * len(configs)]
    for row in results["rows"]:
        cells = [f"{row['name']}@{row['mesh']}"]
        for c in configs:
            r = row["configs"].get(c)
            cells.append("-" if r is None else f"{r['compile_s']:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write(out: Path, results: dict) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    for suffix, text in ((".json", json.dumps(results, indent=1)), (".md", markdown(results))):
        path = out.with_suffix(suffix)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, path)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=None, help="comma-separated entries: " + ", ".join(ENTRIES))
    parser.add_argument("--configs", default=",".join(DEFAULT_CONFIGS), help="comma-separated: " + ", ".join(CONFIGS))
    parser.add_argument("--mesh", default=None, help="a mesh file (default: the bundled spot)")
    parser.add_argument("--out", default=str(RESULTS / "bench_compile_policy"), help="results path without suffix")
    parser.add_argument("--append", action="store_true", help="add rows to the --out JSON instead of replacing it")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per child process")
    parser.add_argument("--render", action="store_true", help="measure nothing: rewrite the --out .md from its .json")
    args = parser.parse_args(argv)
    if args.render:
        write(Path(args.out), json.loads(Path(args.out).with_suffix(".json").read_text()))
        return
    from jaxbvh.io import bundled_mesh_path

    mesh = str(Path(args.mesh).resolve()) if args.mesh else str(bundled_mesh_path())
    tag = Path(mesh).stem
    names = [n.strip() for n in args.only.split(",")] if args.only else list(ENTRIES)
    configs = [c.strip() for c in args.configs.split(",")]
    unknown = [n for n in names if n not in ENTRIES] + [c for c in configs if c not in CONFIGS]
    if unknown:
        parser.error(f"unknown entries or configs: {', '.join(unknown)}")
    out = Path(args.out)
    base_env = child_env(str(ROOT))
    work = Path(tempfile.mkdtemp(prefix="jaxbvh-bench-policy-"))
    spec = {"mesh": mesh, "tree": str(work / "tree.npz"), "rays": str(work / "rays.npz"), "rays_n": RAYS}
    done = subprocess.run([sys.executable, "-c", _PREPARE, json.dumps(spec)], env=dict(base_env, JAXBVH_CACHE="off"),
                          capture_output=True, text=True, timeout=args.timeout)
    if done.returncode != 0:
        raise RuntimeError(f"preparing {mesh} failed: {done.stderr[-3000:]}")
    triangles = json.loads(done.stdout.strip().splitlines()[-1])["triangles"]
    results = {"command": "python bench/bench_compile_policy.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
               "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
               "commit": commit(), "machine": machine(), "load_start": load(), "load_end": None, "jax": None,
               "configs": configs, "flags": {c: CONFIGS[c] for c in configs}, "rows": []}
    if args.append and out.with_suffix(".json").exists():
        results = json.loads(out.with_suffix(".json").read_text())
        results["command"] += " ; " + "python bench/bench_compile_policy.py" + "".join(
            f" {a}" for a in (argv or sys.argv[1:]))
        results["configs"] = list(dict.fromkeys(results["configs"] + configs))
        results["flags"].update({c: CONFIGS[c] for c in configs})
    try:
        for name in names:
            setup, call, work_expr, unit = ENTRIES[name]
            row = {"name": name, "mesh": tag, "triangles": triangles, "unit": unit, "work": None,
                   "load": load(), "configs": {}}
            results["rows"].append(row)
            for config in configs:
                child = {"setup": setup, "call": call, "work": work_expr, "hot": HOT_RUNS, **spec}
                start = time.perf_counter()
                ran = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(child)], env=env_for(config, base_env),
                                     capture_output=True, text=True, timeout=args.timeout, cwd=work)
                lines = [ln for ln in ran.stdout.splitlines() if ln.startswith("POLICY_JSON ")]
                if ran.returncode != 0 or not lines:
                    print(f"{name} {config}: FAILED rc {ran.returncode}: {ran.stderr[-2000:]}", flush=True)
                    continue
                r = json.loads(lines[-1].split(" ", 1)[1])
                results["jax"] = r.pop("jax")
                r["compile_cpu"] = r["cold_cpu"] - r["run_cpu"]
                r["per_s"] = r["work"] / max(r["run_cpu"], 1e-9)
                r["load"] = load()
                r["process_wall"] = time.perf_counter() - start
                row["work"] = r["work"]
                row["configs"][config] = r
                print(f"{name}@{tag} {config:20s} first {r['cold_cpu']:7.2f} CPU s (XLA {r['compile_s']:6.1f} s wall) "
                      f"run {r['run_cpu']:7.3f} CPU s / {r['work']} {unit}  load {r['load']}", flush=True)
                results["load_end"] = load()
                write(out, results)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    results["load_end"] = load()
    write(out, results)
    print(f"wrote {out.with_suffix('.json')} and .md")


if __name__ == "__main__":
    main()
