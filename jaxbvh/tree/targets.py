"""Cost targets: the SAH constants, leaf limit and node width of the tracer a tree is for (issue 40).

The SAH prices a tree as ``Ct`` per node visited and ``Ci`` per primitive tested
(:mod:`jaxbvh.tree.cost`); ``Ct = Ci = 1`` is the papers' proxy. A tracer pays its own
prices, and the wide layouts change the tree before they trace it. A *target* names
those prices:

==============  ======  ======  ========  =====  ==========================================
name            ``ct``  ``ci``  max_leaf  width  the tracer
==============  ======  ======  ========  =====  ==========================================
``sah``         1       1       default   2      none: the classic SAH (the default)
``tinybvh-*``   fitted  1       4         2/4/8  tinybvh v1.6.7's one-thread kernels
==============  ======  ======  ========  =====  ==========================================

* ``ct``, ``ci``: the constants the builders and the binary optimizers use. Costs are in
  units of one triangle test (``ci = 1``); only the ratio changes which tree is best.
* ``max_leaf``: the most primitives per leaf. tinybvh's wide conversions
  (``BVH4_CPU``, ``BVH8_CPU``: ``ConvertFrom`` after ``CombineLeafs(4)`` and
  ``SplitLeafs(4)``) keep leaves of at most 4.
* ``width``: children per node of the layout the tracer runs (2: binary).
* ``node_ct``: the cost of visiting one node *of that layout* (a wide node tests all its
  children's boxes in one SIMD group); equal to ``ct`` for binary layouts. For a wide
  layout ``ct`` is instead fitted against the visits of the binary tree the optimizers
  see, so that the binary SAH they lower tracks the wide tree's cost.
* The wide kernels test a leaf's up to 4 triangles at once: their price is per leaf
  visit. The SAH prices leaves per triangle, so a wide target's ``ci = 1`` stands for the
  leaf-visit price divided by the mean triangles per leaf visit of the calibration (3.2).

The ``tinybvh-*`` numbers come from ``bench/calibrate_targets.py`` (its result and the
fit's error: ``bench/results/targets.md``): time per ray in each kernel against the
node visits and triangle tests counted by :mod:`jaxbvh.rays` on the tree that kernel
runs, over several trees and ray sets.

:func:`costs` resolves a target with explicit values (explicit values win: ``--target
tinybvh-bvh8 --ct 2`` is that target with ``ct`` 2). :func:`target_cost` prices a tree
for a target: for a binary target its SAH with the target's constants; for a wide one
the SAH of the tree the layout traces, after the layout's leaf merge (every subtree of
at most ``max_leaf`` primitives one leaf, as tinybvh's ``CombineLeafs`` does) and
collapse to ``width`` children (:func:`jaxbvh.wide.collapse.optimal` with ``T(k) =
node_ct * ceil(k / width)``: the least cost over collapses; tinybvh's own collapse is
greedy and can only cost more).

What it buys (issue 40, ``docs/optimizers.md``): the wide targets' ``ct`` barely moves
the wide cost of the pipeline's result (under 1% on spot for ``ct`` from 0.5 to 3,
``bench/results/target_proxy.md``), and a tree optimized for ``tinybvh-bvh8`` was not
measurably faster in ``BVH8_CPU`` than the default tree (``bench/results/
bench_render_targets*.md``). The binary targets set the leaf test and the optimizers'
prices directly.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from jaxbvh.configs import DEFAULT_MAX_LEAF
from jaxbvh.optimize.leaves import merge_leaves
from jaxbvh.tree.cost import sah
from jaxbvh.tree.layout import to_jax
from jaxbvh.wide.box_tests import node_test_cost
from jaxbvh.wide.collapse import optimal

#: the target every command and function uses unless told otherwise
DEFAULT_TARGET = "sah"
#: tinybvh's wide conversions merge every subtree of at most this many primitives (CombineLeafs(4))
TINYBVH_WIDE_LEAF = 4


@dataclasses.dataclass(frozen=True)
class Target:
    """A cost target (module docstring): ``ct``, ``ci`` (SAH constants of the builders
    and binary optimizers, in triangle tests), ``max_leaf``, ``width`` (children per node
    of the traced layout), ``node_ct`` (cost of one visit of a node of that layout),
    ``merge_leaves`` (the layout merges every subtree of at most ``max_leaf`` primitives
    before tracing), ``tracer`` (what the numbers were fitted on)."""

    name: str
    ct: float
    ci: float
    max_leaf: int
    width: int
    node_ct: float
    merge_leaves: bool
    tracer: str


#: every target by name (the command line's ``--target``). tinybvh numbers: the table "The
#: targets" of bench/results/targets.md (bench/calibrate_targets.py; legocar and spot, 8 trees
#: each, 3 ray sets; fit error RMS 6-9%). The wide kernels' node and leaf prices rise
#: together across trees (correlation ~0.9), so their ratio is known only roughly.
TARGETS: dict[str, Target] = {t.name: t for t in (
    Target("sah", 1.0, 1.0, DEFAULT_MAX_LEAF, 2, 1.0, False, "the classic SAH, Ct = Ci = 1"),
    Target("tinybvh-bvh", 0.81, 1.0, DEFAULT_MAX_LEAF, 2, 0.81, False, "tinybvh BVH::Intersect"),
    Target("tinybvh-soa", 0.99, 1.0, DEFAULT_MAX_LEAF, 2, 0.99, False, "tinybvh BVH_SoA::Intersect (AVX)"),
    Target("tinybvh-bvh4", 2.85, 1.0, TINYBVH_WIDE_LEAF, 4, 3.92, True, "tinybvh BVH4_CPU::Intersect (AVX2)"),
    Target("tinybvh-bvh8", 1.92, 1.0, TINYBVH_WIDE_LEAF, 8, 3.95, True, "tinybvh BVH8_CPU::Intersect (AVX2)"),
)}


def get(target: str | Target | None) -> Target:
    """The :class:`Target` named ``target`` (None: :data:`DEFAULT_TARGET`; a Target: itself);
    ``ValueError`` listing the names for an unknown one."""
    if isinstance(target, Target):
        return target
    name = DEFAULT_TARGET if target is None else target
    if name not in TARGETS:
        raise ValueError(f"unknown target {name!r}; choose one of {', '.join(TARGETS)}")
    return TARGETS[name]


def costs(target: str | Target | None = None, *, ct: float | None = None, ci: float | None = None,
          max_leaf: int | None = None) -> dict:
    """``{"ct", "ci", "max_leaf"}`` of ``target`` with every value given explicitly in its place."""
    t = get(target)
    return {"ct": t.ct if ct is None else ct, "ci": t.ci if ci is None else ci,
            "max_leaf": t.max_leaf if max_leaf is None else max_leaf}


def target_cost(tree, target: str | Target | None = None, *, ct: float | None = None,
                ci: float | None = None, max_leaf: int | None = None) -> float:
    """The cost of ``tree`` (a binary :class:`~jaxbvh.tree.layout.BVH`) for ``target``
    (module docstring), in triangle tests per ray that hits the root box, as a float.

    ``ct``, ``ci``, ``max_leaf``: explicit values in place of the target's. A wide
    target prices its nodes with ``node_ct``: ``ct``, the binary optimizers' constant,
    does not enter its cost.
    """
    t = get(target)
    c = costs(t, ct=ct, ci=ci, max_leaf=max_leaf)
    if t.width == 2 and not t.merge_leaves:
        return float(sah(tree, c["ct"], c["ci"]))
    return float(_wide_cost(tree, t.width, t.node_ct, c["ci"], c["max_leaf"], t.merge_leaves))


def _wide_cost(tree, width, node_ct, ci, max_leaf, merge):
    """The SAH of ``tree`` after merging every subtree of at most ``max_leaf`` primitives
    (when ``merge``) and the least-cost collapse to ``width`` children."""
    jtree = to_jax(tree)
    dtype = jtree.lo.dtype
    if merge and max_leaf > 1:
        # a Ct above every mergeable leaf's cost makes each allowed merge the cheaper
        # choice: the pass then merges every subtree of at most max_leaf primitives, as
        # the layout's conversion does whatever it costs
        prohibitive = jnp.asarray(max_leaf + 1, dtype)
        jtree = merge_leaves(jtree, jnp.int32(max_leaf), prohibitive, jnp.asarray(1, dtype))
    groups = node_test_cost(width)
    result = optimal(jtree, max_children=width, test_cost=lambda k: node_ct * groups(k), ci=ci)
    # R prices every visit of a kept node (its children's boxes); the root's own box is
    # the ray's entry test, which the SAH does not count either
    return result.rcost + result.leaf_cost
