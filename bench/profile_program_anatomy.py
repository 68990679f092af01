"""Where the operations of a call's compiled programs come from (program anatomy).

    python bench/profile_program_anatomy.py build:sbvh [twolevel:build collapse:optimal ...]
        [--depth 3] [--top 25] [--json FILE]

Runs each entry of :mod:`bench.bench_compile` (same setup and call source) in this
process with jaxbvh's stores off (``JAXBVH_CACHE=off``: plain ``jax.jit``, so programs keep
their function names) and counts, for every program sent to XLA, its StableHLO
operations as ``bench/bench_compile.py`` does (every op but ``builtin.module``,
``func.func`` and the ``func.return`` / ``stablehlo.return`` terminators), then
attributes each op to its Python source: the chain of jaxbvh frames in the op's MLIR
location (``jax_traceback_in_locations_limit`` raised so the chain is whole), outermost
first. Printed per program: ops by innermost jaxbvh function, and by the chain's first
``--depth`` frames below the program's entry function (the stage of the level that
asked for them; ops of a nested jit's body carry only the frames below it). An op inside a function called through ``func.call`` (a nested jit)
is counted once, as XLA is given it. Op counts are sizes before XLA's optimizations;
they are what a compile's time grows with, not a measure of run time.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("JAXBVH_CACHE", "off")

_SKIP = {"builtin.module", "func.func", "func.return", "stablehlo.return"}
# a frame in an MLIR location: "function"("file":line:col ...
_FRAME = re.compile(r'"([^"()]+)"\("([^"]+)":(\d+)')


def _frames(location: str) -> list[tuple[str, str, int]]:
    """The jaxbvh frames ``(function, file, line)`` of an op's location, outermost first."""
    found = [(f, path, int(line)) for f, path, line in _FRAME.findall(location) if "/jaxbvh/" in path]
    return found[::-1]  # MLIR callsites list the innermost frame first


def _label(frame) -> str:
    function, path, line = frame
    module = path.split("/jaxbvh/", 1)[1].removesuffix(".py").replace("/", ".")
    return f"{module}.{function}:{line}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("entries", nargs="+")
    parser.add_argument("--depth", type=int, default=3)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--min-ops", type=int, default=100, help="programs smaller than this are listed only")
    parser.add_argument("--json")
    args = parser.parse_args()

    import jax
    jax.config.update("jax_traceback_in_locations_limit", 64)
    from jax._src.interpreters import mlir as _mlir
    from jax._src.lib.mlir import ir as _ir

    programs: list[dict] = []
    dump = _mlir.dump_module_to_file

    def counting_dump(module, stage):
        ops = []

        def visit(op):
            if op.name not in _SKIP:
                ops.append((op.name, str(op.location)))
            return _ir.WalkResult.ADVANCE

        module.operation.walk(visit)
        name = _ir.StringAttr(module.operation.attributes["sym_name"]).value
        programs.append({"name": name, "ops": ops})
        return dump(module, stage)

    _mlir.dump_module_to_file = counting_dump

    import jaxbvh
    from bench.bench_compile import entries
    from jaxbvh.io import bundled_mesh_path

    table = entries(str(bundled_mesh_path()), "spot")
    report = {}
    for entry in args.entries:
        spec = table[entry]
        scope = {"spec": {"mesh": str(bundled_mesh_path())}, "jax": jax, "jaxbvh": jaxbvh}
        if "tree" in spec["setup"]:  # a sweep tree, as bench_compile prepares it
            lo_hi = "from jaxbvh.io import load_mesh\nmesh = load_mesh(spec['mesh'])\nlo, hi = mesh.local_boxes()\n"
            exec(lo_hi + "tree = jaxbvh.build(lo, hi, method='sweep')\n", scope)
            setup = ""
        else:
            setup = spec["setup"]
        exec(setup, scope)
        programs.clear()
        exec(spec["call"], scope)
        jax.effects_barrier()
        print(f"\n=== {entry}: {len(programs)} programs, {sum(len(p['ops']) for p in programs):,} ops")
        rows = []
        for p in programs:
            print(f"  {p['name']}: {len(p['ops']):,} ops")
            if len(p["ops"]) < args.min_ops:
                continue
            by_inner = collections.Counter()
            by_path = collections.Counter()
            by_kind = collections.Counter()
            entry_name = p["name"].removeprefix("jit_")
            for kind, loc in p["ops"]:
                frames = _frames(loc)
                by_kind[kind] += 1
                by_inner[_label(frames[-1]) if frames else "(no jaxbvh frame)"] += 1
                # below the program's own function: the stage that asked for the op
                entry_at = [i for i, f in enumerate(frames) if f[0] == entry_name]
                below = frames[entry_at[-1] + 1:] if entry_at else frames
                path = below[:args.depth]
                by_path[" > ".join(_label(f).split(":")[0] for f in path) or "(none)"] += 1
            print(f"    by stage (first {args.depth} jaxbvh frames below the entry):")
            for key, n in by_path.most_common(args.top):
                print(f"      {n:6,d}  {key}")
            print("    by innermost jaxbvh line:")
            for key, n in by_inner.most_common(args.top):
                print(f"      {n:6,d}  {key}")
            print("    by op kind:", ", ".join(f"{k.split('.')[-1]} {n}" for k, n in by_kind.most_common(12)))
            rows.append({"name": p["name"], "ops": len(p["ops"]), "by_stage": dict(by_path),
                         "by_line": dict(by_inner), "by_kind": dict(by_kind)})
        report[entry] = {"programs": [(p["name"], len(p["ops"])) for p in programs], "anatomy": rows}
    if args.json:
        from jaxbvh.files import atomic_write
        atomic_write(args.json, json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
