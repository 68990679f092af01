"""Where the optimizers' compiled programs get their size: operations per function.

For issue 38 (compile time). For each optimizer (its ``optimize:<method>:first`` settings
of ``bench/bench_compile.py``: one pass / iteration / round) on a sweep tree of the
bundled mesh, this lowers the two programs the driver runs, the loop of steps
(``driver.advance``) and ``result`` (``driver.finish``), and the programs ``init`` runs,
and reports:

- ``hlo``: operations of the lowered StableHLO module (the size XLA is given; counted as
  ``bench/bench_compile.py`` counts them: every op but the module, function and return
  wrappers);
- ``eqns``: equations of the program's jaxpr, counted recursively into every sub-jaxpr
  (while / cond / scan bodies, inner jits), each control-flow equation itself counted once;
- per function of ``jaxbvh`` (file:function), *inclusive* jaxpr equations (every equation
  traced while that function was on the Python stack) and ``copies``: how many distinct
  call sites (distinct caller stacks) traced it into this program, so a sub-computation
  duplicated by an unrolled Python loop or called from two places shows as copies > 1.

Nothing is compiled (lowering only), so it runs in seconds. Run::

    python bench/profile_optimizers_anatomy.py                     # hc, sa, reinsert, treelet, pipeline
    python bench/profile_optimizers_anatomy.py --only pipeline --top 40
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("JAXBVH_CACHE", "off")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from jax._src import core as jcore  # noqa: E402
import numpy as np  # noqa: E402

_SKIP = {"builtin.module", "func.func", "func.return", "stablehlo.return"}

from bench.bench_compile import FIRST_PASS  # noqa: E402 (each optimizer stopped after its first pass)


def hlo_ops(lowered) -> int:
    module = lowered.compiler_ir("stablehlo")
    n = [0]

    def visit(op):
        if op.name not in _SKIP:
            n[0] += 1
        from jax._src.lib.mlir import ir
        return ir.WalkResult.ADVANCE

    module.operation.walk(visit)
    return n[0]


def _subjaxprs(eqn):
    for value in eqn.params.values():
        for v in (value if isinstance(value, (tuple, list)) else (value,)):
            if isinstance(v, jcore.ClosedJaxpr):
                yield v.jaxpr
            elif isinstance(v, jcore.Jaxpr):
                yield v


def _jaxbvh_stack(eqn):
    """The jaxbvh frames of ``eqn``'s traceback, outermost first: (file:function, line)."""
    tb = eqn.source_info.traceback
    if tb is None:
        return []
    out = []
    for code, lasti in zip(tb.raw_frames()[0], tb.raw_frames()[1]) if hasattr(tb, "raw_frames") else []:
        fname = code.co_filename
        if "/jaxbvh/" not in fname or "/bench/" in fname:
            continue
        line = code.co_firstlineno
        name = f"{fname.split('/jaxbvh/')[-1]}:{code.co_name}"
        out.append((name, line, lasti))
    return out[::-1]


def anatomy(jaxpr):
    """(eqns, inclusive {function: eqns}, copies {function: call sites})."""
    total = [0]
    inclusive = collections.Counter()
    sites = collections.defaultdict(set)

    def walk(jx):
        for eqn in jx.eqns:
            subs = list(_subjaxprs(eqn))
            total[0] += 1
            stack = _jaxbvh_stack(eqn)
            seen = set()
            for k, (name, _, _) in enumerate(stack):
                if name in seen:
                    continue
                seen.add(name)
                inclusive[name] += 1
                sites[name].add(tuple((n, l) for n, _, l in stack[:k]))
            for sub in subs:
                walk(sub)

    walk(jaxpr)
    return total[0], inclusive, {k: len(v) for k, v in sites.items()}


def programs_of(method: str, tree):
    """[(label, fun, args)] of the programs the driver runs for ``method``."""
    from jaxbvh.optimize import OPTIMIZERS, make_config
    from jaxbvh.optimize import driver

    opt = OPTIMIZERS[method]
    config = make_config(method, None, **FIRST_PASS[method])
    state = opt.init(tree, config, None)
    stop = jnp.int32(0)
    out = [("step loop", lambda s, n: driver._advance(opt.step, s, n), (state, stop))]
    if opt.advance is not None:  # the pipeline: what its host loop runs instead
        from jaxbvh.optimize import pipeline
        for index, name in enumerate(pipeline.STAGES):
            sub = getattr(state.inner, name)
            step = pipeline._STAGE_OPTIMIZERS[index].step
            out.append((f"{name} stage loop", lambda s, n, step=step: driver._advance(step, s, n), (sub, stop)))
            out.append((f"{name} absorb", lambda s, t, f, index=index: pipeline._absorb.fun(s, t, f, index),
                        (state, sub, stop)))
        out.append(("settle", pipeline._settled, (state,)))
    return out + [("finish", opt.result, (state,))]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="hc,sa,reinsert,treelet,pipeline")
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--mesh", default=None)
    args = parser.parse_args(argv)
    import jaxbvh
    from jaxbvh.io import bundled_mesh_path, load_mesh

    mesh = load_mesh(args.mesh or bundled_mesh_path())
    lo, hi = mesh.local_boxes()
    tree = jax.device_get(jaxbvh.build(lo, hi, method="sweep"))
    for method in args.only.split(","):
        for label, fun, fargs in programs_of(method, tree):
            lowered = jax.jit(fun).lower(*fargs)
            closed = jax.make_jaxpr(fun)(*fargs)
            eqns, inclusive, copies = anatomy(closed.jaxpr)
            print(f"\n## {method}: {label}  hlo {hlo_ops(lowered):,}  eqns {eqns:,}")
            print(f"{'eqns':>7} {'share':>6} {'copies':>6}  function")
            for name, n in inclusive.most_common(args.top):
                print(f"{n:7d} {n / eqns:6.1%} {copies[name]:6d}  {name}")
            sys.stdout.flush()


if __name__ == "__main__":
    main()
