"""CPU seconds of what issue 39's precision changes touch: the compile and the steps of
``sa`` and ``reinsert`` (costs now rounded product by product and summed in one order,
jaxbvh.numerics.rounded / ordered_sum) and the binned build (half_area, outward
narrowing). Run it on two checkouts to compare (``PYTHONPATH=<checkout> python
bench/bench_rounded_costs.py``), in a plain process (no test XLA flags); the compile
cache is off so that every compile is cold. Prints one JSON line; say the load.

Measures CPU seconds of this process (user + system), not wall time: the machine is
shared.
"""

from __future__ import annotations

import json
import os
import resource
import sys

os.environ["JAXBVH_CACHE"] = "off"

import jax  # noqa: E402

import jaxbvh  # noqa: E402
from jaxbvh.io import bundled_mesh_path, load_mesh  # noqa: E402
from jaxbvh.optimize import OPTIMIZERS  # noqa: E402


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(fn):
    start = cpu()
    out = jax.block_until_ready(fn())
    return out, cpu() - start


def main(steps: int = 5) -> dict:
    lo, hi = load_mesh(bundled_mesh_path()).local_boxes()
    row = {"mesh": "spot", "triangles": int(lo.shape[0]), "load": os.getloadavg()[0]}
    tree, row["binned_build_first_cpu_s"] = timed(lambda: jaxbvh.build(lo, hi, method="binned"))
    _, row["binned_build_again_cpu_s"] = timed(lambda: jaxbvh.build(lo, hi, method="binned"))
    for name in ("sa", "reinsert"):
        optimizer = OPTIMIZERS[name]
        state = optimizer.init(tree, optimizer.Config(), jax.random.key(0))
        step = jax.jit(optimizer.step)
        state, row[f"{name}_first_step_cpu_s"] = timed(lambda: step(state))  # compile + one step
        start = cpu()
        for _ in range(steps):
            state = step(state)
        jax.block_until_ready(state)
        row[f"{name}_step_cpu_s"] = (cpu() - start) / steps
    row["load_after"] = os.getloadavg()[0]
    return row


if __name__ == "__main__":
    print(json.dumps(main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)))
