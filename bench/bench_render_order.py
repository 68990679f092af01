"""Child order in tinybvh's kernels: the same tree with its siblings swapped, seen from both sides (issue 40).

    python bench/bench_render_order.py --meshes fandisk /tmp/interior.obj --res 384 --repeats 5
    python bench/bench_render_order.py --meshes legocar --rules count_asc flip --reuse

Swapping the two children of a node changes no box and no hit, only the order in which
a kernel visits them when it cannot tell them apart: tinybvh's binary kernels
(``BVH::Intersect``, ``BVH_SoA::Intersect``) visit the left child first when both
children's entry distances are equal (a ray entering both boxes through one shared face,
or starting inside both), and the wide kernels (``BVH4_CPU``, ``BVH8_CPU``) break ties of
their per-octant child order by the child's slot. This script measures how much that
order is worth, and whether a rule that sets it serves every scene:

* our trees as ``bench_render.py`` makes them (``ours_default``, ``ours_sbvh``, written by
  ``jaxbvh export --format tinybvh``), and copies with their sibling records swapped by a
  rule (:data:`RULES`; a relabeling of the node file: same boxes, same leaves);
* one tracer run over all of them and tinybvh's trees (``../shared/peer/tinybvh_trace``,
  thread CPU time, min over ``--repeats``);
* a second run on the scene point-reflected through the origin (every coordinate negated,
  triangles and our node files alike; tinybvh's trees are built again by the tracer on the
  reflected triangles): the tracer's camera sits on one fixed oblique axis, so this is our
  same trees seen from the opposite side.

Writes ``bench/results/bench_render_order.{json,md}`` (``--name`` renames them): per mesh,
orientation, rule and layout the Mrays/s ratio to the tree in its exported order
(geomean over the primary, random and bounce rays, and the primary rays alone).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_render as br  # noqa: E402

#: tinybvh::BVH::BVHNode as the node file stores it (jaxbvh.io.tinybvh.NODE_DTYPE)
NODE = np.dtype([("lo", "<f4", (3,)), ("first", "<u4"), ("hi", "<f4", (3,)), ("count", "<u4")])
#: rule -> what goes left. Keys are per node; the child with the smaller key goes left.
RULES = {
    "flip": "every pair swapped (the exported order reversed)",
    "count_asc": "the child with fewer primitives first",
    "cost_asc": "the child of lower subtree SAH cost (Ct = Ci = 1) first",
    "area_desc": "the child of larger box surface first",
}


def read_nodes(path: Path):
    """``(data, nodes, used, prim, tris)`` of a TBVHNOD1 file: its bytes, NODE [used] (a
    copy), primIdx uint32 [idx], triangles float32 [n, 3, 3]."""
    data = path.read_bytes()
    if data[:8] != b"TBVHNOD1":
        raise ValueError(f"{path}: not a TBVHNOD1 node file")
    used, idx, tri, _ = (int(x) for x in np.frombuffer(data, "<u4", 4, 8))
    nodes = np.frombuffer(data, NODE, used, 24).copy()
    prim = np.frombuffer(data, "<u4", idx, 24 + 32 * used)
    tris = np.frombuffer(data, "<f4", tri * 9, 24 + 32 * used + 4 * idx).reshape(tri, 3, 3)
    return data, nodes, used, prim, tris


def relabel(src: Path, dst: Path, rule: str) -> None:
    """Write ``src`` with each sibling pair's records in the order ``rule`` gives.

    Swapping two sibling records keeps every link valid (a record carries its own
    children's slot), and each subtree's primIdx run stays contiguous."""
    data, nodes, used, _, _ = read_nodes(src)
    preorder, stack = [], [0]
    while stack:
        n = stack.pop()
        preorder.append(n)
        if nodes["count"][n] == 0:
            stack += [int(nodes["first"][n]), int(nodes["first"][n]) + 1]
    ext = np.maximum(nodes["hi"].astype(np.float64) - nodes["lo"], 0.0)
    half_area = ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 2] * ext[:, 0]
    count = nodes["count"].astype(np.float64)
    cost = count.copy()
    for n in reversed(preorder):  # children before parents
        if nodes["count"][n] == 0:
            f = int(nodes["first"][n])
            count[n] = count[f] + count[f + 1]
            cost[n] = 1.0 + (half_area[f] * cost[f] + half_area[f + 1] * cost[f + 1]) / max(half_area[n], 1e-300)
    key = {"flip": None, "count_asc": count, "cost_asc": cost, "area_desc": -half_area}[rule]
    for n in preorder:  # a pair is swapped before either child is visited: each record moves once
        if nodes["count"][n] != 0:
            continue
        f = int(nodes["first"][n])
        if key is None or key[f + 1] < key[f]:
            nodes[[f, f + 1]] = nodes[[f + 1, f]]
            if key is not None:
                key[[f, f + 1]] = key[[f + 1, f]]
    dst.write_bytes(data[:24] + nodes.tobytes() + data[24 + 32 * used:])


def reflect_triangles(src: Path, dst: Path) -> None:
    """The tracer's triangle file (uint32 n, float32 [n, 3, 3]) with every coordinate negated."""
    data = src.read_bytes()
    n = int(np.frombuffer(data, "<u4", 1)[0])
    tris = np.frombuffer(data, "<f4", n * 9, 4)
    dst.write_bytes(data[:4] + (-tris).astype("<f4").tobytes() + data[4 + 36 * n:])


def reflect_nodes(src: Path, dst: Path) -> None:
    """A node file with every coordinate negated (a box [lo, hi] becomes [-hi, -lo]: negation
    is exact in float32, so containment holds as before)."""
    data, nodes, used, _, tris = read_nodes(src)
    lo, hi = nodes["lo"].copy(), nodes["hi"].copy()
    nodes["lo"], nodes["hi"] = -hi, -lo
    start = len(data) - tris.nbytes
    dst.write_bytes(data[:24] + nodes.tobytes() + data[24 + 32 * used:start] + (-tris).astype("<f4").tobytes())


def trace(exe: Path, tris: Path, trees: dict, args) -> tuple[list, dict]:
    cmd = [str(exe), str(tris), "--peer", ",".join(br.PEERS), "--layouts", ",".join(br.LAYOUTS),
           "--repeats", str(args.repeats), "--res", str(args.res), "--seed", str(args.seed)]
    for name, path in trees.items():
        cmd += ["--tree", f"{name}={path}"]
    started = br.load()
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    lines = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    return lines, {"load_start": started, "load_end": br.load()}


def ratios(lines: list, rules: list, bases: list) -> dict:
    """``{base: {rule: {layout: {"all": geomean ratio, "primary": ratio}}}}``: each relabeled
    tree over its base tree, and each base over tinybvh's best (``"vs_tinybvh"``)."""
    got = {(x["tree"], x["layout"], x["set"]): x["mrays_per_s"] for x in lines if x["kind"] == "trace"}
    summary = br.summarize(lines)
    out = {}
    for base in bases:
        row = {"vs_tinybvh": {lay: summary["trees"][base][lay]["vs_tinybvh_best"] for lay in br.LAYOUTS}}
        for rule in rules:
            name = f"{base}.{rule}"
            row[rule] = {lay: {"all": br.geomean(got[(name, lay, s)] / got[(base, lay, s)] for s in br.SETS),
                               "primary": got[(name, lay, "primary")] / got[(base, lay, "primary")]}
                         for lay in br.LAYOUTS}
        out[base] = row
    out["disagreements"] = summary["disagreements"]
    return out


def one_mesh(name: str, args, exe: Path) -> dict:
    path = Path(br.INPUTS.get(name, name))
    path = path if path.is_absolute() or path.exists() else br.DATA / path
    work = args.work / path.stem
    (work / "reflected").mkdir(parents=True, exist_ok=True)
    bases = {tree: br.our_tree(path, tree, opts, work, args.reuse) for tree, opts in br.OURS.items()}
    tris = work / "tris.bin"
    subprocess.run([sys.executable, str(br.PEER / "dump_tris.py"), str(path), str(tris)], check=True,
                   capture_output=True)
    result = {"mesh": name, "path": str(path), "utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
              "ours": bases, "orientations": {}}
    for side in ("as_is", "reflected"):
        trees = {}
        for base, info in bases.items():
            trees[base] = Path(info["file"])
            for rule in args.rules:
                trees[f"{base}.{rule}"] = work / f"{base}.{rule}.bin"
                relabel(trees[base], trees[f"{base}.{rule}"], rule)
        here = tris
        if side == "reflected":
            here = work / "reflected" / "tris.bin"
            reflect_triangles(tris, here)
            for tree, file in list(trees.items()):
                trees[tree] = work / "reflected" / file.name
                reflect_nodes(file, trees[tree])
        print(f"{name}: tracing {side} (load {br.load()})", file=sys.stderr, flush=True)
        lines, loads = trace(exe, here, trees, args)
        result["orientations"][side] = {"lines": lines, **loads, **ratios(lines, args.rules, list(bases))}
    return result


def markdown(report: dict) -> str:
    out = ["# Child order in tinybvh's kernels (`bench/bench_render_order.py`)", "",
           f"{report['machine']}; tinybvh v1.6.7 kernels, one thread; {report['res']}² rays per set, min of "
           f"{report['repeats']} rounds of thread CPU time; from {report['utc']} UTC. Our trees as "
           "`bench_render.py` makes them, then relabeled: each sibling pair's records swapped by a rule "
           "(same boxes, same leaves, same hits). *as is*: the tracer's scene; *reflected*: every coordinate "
           "negated (our same trees reflected; tinybvh's built again), i.e. seen by the tracer's fixed camera "
           "from the opposite side.", "",
           "Rules: " + "; ".join(f"`{k}`: {RULES[k]}" for k in report["rules"]) + ".", "",
           "Cells: relabeled tree / the same tree in its exported order, Mrays/s, geomean over primary, random "
           "and bounce rays (in brackets: primary rays alone). The `order as exported` rows give that tree "
           "over tinybvh's best tree in the layout (geomean).", ""]
    for r in report["meshes"]:
        out += [f"## {r['mesh']}", "",
                "| orientation | tree | rule | " + " | ".join(br.LAYOUT_CLASS[x] for x in br.LAYOUTS) + " |",
                "|---|---|---|" + "---|" * len(br.LAYOUTS)]
        for side, o in r["orientations"].items():
            for base in r["ours"]:
                out.append(f"| {side} | {base} | order as exported (vs tinybvh's best) | "
                           + " | ".join(f"{o[base]['vs_tinybvh'][x]:.3f}" for x in br.LAYOUTS) + " |")
                for rule in report["rules"]:
                    out.append(f"| {side} | {base} | {rule} | " + " | ".join(
                        f"{o[base][rule][x]['all']:.3f} ({o[base][rule][x]['primary']:.3f})" for x in br.LAYOUTS) + " |")
        loads = "; ".join(f"{side} load {o['load_start']} → {o['load_end']}" for side, o in r["orientations"].items())
        bad = sum(len(o["disagreements"]) for o in r["orientations"].values())
        out += ["", f"{loads}. Traces whose hits differ from tinybvh's `Build` tree (another t or hit/miss): {bad}.", ""]
    return "\n".join(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", nargs="+", default=["legocar", "fandisk"])
    parser.add_argument("--rules", nargs="+", default=["flip", "count_asc"], choices=list(RULES))
    parser.add_argument("--res", type=int, default=384)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "jaxbvh-bench-render")
    parser.add_argument("--reuse", action="store_true", help="reuse our trees already in --work")
    parser.add_argument("--name", default="bench_render_order")
    parser.add_argument("--peer-build", type=Path, default=Path("/tmp/jaxbvh-peer"))
    args = parser.parse_args(argv)
    exe = br.tracer(args.peer_build)
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "")
    report = {"machine": f"{cpu}, 2 cores, shared", "utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
              "res": args.res, "repeats": args.repeats, "rules": args.rules, "meshes": []}
    from jaxbvh.files import atomic_write

    for name in args.meshes:
        report["meshes"].append(one_mesh(name, args, exe))
        with atomic_write(br.RESULTS / f"{args.name}.json", "w") as f:
            json.dump(report, f, separators=(",", ":"))  # the raw tracer lines make it large
        with atomic_write(br.RESULTS / f"{args.name}.md", "w") as f:
            f.write(markdown(report))
        print(markdown(report), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
