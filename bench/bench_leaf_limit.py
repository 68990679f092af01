"""Which leaf limit (``max_leaf``) the defaults should use: sweep build, then the pipeline.

    python bench/bench_leaf_limit.py MESH [L,M ...]     # e.g. drone.gltf 4,4 8,8 16,16

For each ``L,M``: ``jaxbvh.build(lo, hi, SweepConfig(max_leaf=L))`` then
``optimize(tree, "pipeline", max_leaf=M)`` (its final exact leaf merge at ``M``); prints the
build's and the result's SAH (Ct = Ci = 1, root-area normalised), the largest and mean leaf,
and the CPU seconds of the pair (the first pair of a process includes compiling). The
table in ``bench/results/leaves.md`` ("The leaf limit, 4 / 8 / 16") comes from it.
"""

import sys
import time

import numpy as np

import jaxbvh
from jaxbvh.builders import SweepConfig
from jaxbvh.io import load_mesh


def main(argv):
    mesh = load_mesh(argv[0])
    lo, hi = mesh.local_boxes()
    for pair in argv[1:] or ["4,4", "8,8", "16,16"]:
        build_leaf, merge_leaf = map(int, pair.split(","))
        t0 = time.process_time()
        tree = jaxbvh.build(lo, hi, SweepConfig(max_leaf=build_leaf))
        result = jaxbvh.optimize.optimize(tree, "pipeline", max_leaf=merge_leaf)
        count = np.asarray(result.tree.prim_count)
        leaves = count[count > 0]
        print(f"{mesh.name}: build L {build_leaf}, merge {merge_leaf}: SAH {float(jaxbvh.sah(tree)):.3f} -> "
              f"{float(result.sah):.4f}, leaves max {leaves.max()} mean {leaves.mean():.2f}, "
              f"CPU {time.process_time() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
