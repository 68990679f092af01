"""Adaptive collapsing of a binary BVH into a wide one (Susano Pinto 2010).

Cost model
==========
Pinto's ray cost of a wide tree, in root-normalised areas ``a(n) = S(n) / S(root)``
(``S`` the surface area of the box; ``a = 1`` everywhere when the root has zero area, as
:mod:`jaxbvh.tree.cost` treats a zero-area node)::

    R = sum over interior nodes m of  a(m) * T(k_m)

``k_m`` is the number of children of ``m`` and ``T(k)`` the cost of testing ``k`` child
boxes together: ``T(k) = k`` (one box at a time, the paper's R_cost) or
``T(k) = ceil(k / w)`` (``w``-wide SIMD group test), see :func:`node_test_cost`; any
function of ``k`` that works on int arrays is accepted. ``R`` is the expected number of
box tests of a ray that hits the root box and finds every hit (the root's own test is
not counted). A *collapse* removes interior non-root nodes: a kept node's children
become its nearest kept descendants. Leaves are never removed (the paper's rule), so
the primitive tests ``Ci * sum a(leaf) * count(leaf)`` (:func:`leaf_cost`) do not
change and are reported apart. Only with ``max_leaf > 1`` (beyond the paper, see
:func:`optimal`) does a collapse change the leaves; the DP then minimises
``R + leaf_cost``.

Methods
=======
* :func:`greedy` — the paper's Algorithm 2, top-down pushup: a child ``c`` of a kept
  node ``n`` is collapsed into ``n`` when ``1 + P(c|n) k_c >= k_c`` with
  ``P(c|n) = a(c) / a(n)`` (the condition for constant ``T``; for a binary input
  ``P >= 1/2``), its children then examined against ``n`` in turn (first in, first
  out); otherwise ``c`` is kept and pushed up itself. Leaves are always kept. With
  ``max_children = K`` a collapse that would give ``n`` more than ``K`` children is not
  taken. The rule is the paper's whatever ``T``; ``T`` only prices the result.
* :func:`optimal` — the paper's Algorithm 3, the least ``R`` over all collapses with at
  most ``K`` children per node (``MAX_CHILDS``; default 8, the paper used 15). For every
  node and every ``t <= K``, ``g(n, t)`` is the least cost of ``n``'s subtree seen by its
  kept ancestor as *exactly* ``t`` entry points (Pinto's table holds "at most ``t``";
  "exactly" lets any ``T``, not only a non-decreasing one, be priced right)::

      leaf:      g(n, 1) = 0,  g(n, t > 1) = inf
      interior:  h(n, t) = min over i of g(L, i) + g(R, t - i)      (n removed)
                 g(n, 1) = min over t = 2..K of a(n) T(t) + h(n, t)  (n kept)
                 g(n, t) = h(n, t) for t >= 2

  ``R = g(root, 1)``. The tables are solved bottom-up one depth at a time, every node
  of a depth at once (a vectorised min-plus product of the two children's [nodes, K+1]
  tables), and the choices are back-tracked top-down, also one depth at a time
  (:mod:`jaxbvh.wide.levels`). Work O(nodes K^2), linear in the number of nodes.
* :func:`qbvh` — the paper's baseline: every interior node at odd depth removed (4-wide).

Tie rule (the NumPy twin :mod:`jaxbvh.wide.collapse_reference` keeps the same one). XLA on
CPU fuses multiply-adds, so a cost can come out a few ulps apart here and in NumPy; and
splits in the middle of a box (binned builders) make candidates that are equal in exact
arithmetic but differ by up to ~10 ulps in float32. Costs within a relative
:func:`jaxbvh.numerics.min_gain` (``64 eps``: 7.6e-6 in float32, as :mod:`jaxbvh.optimize.rotate`'s margin)
count as equal and the first candidate wins: the lowest ``i`` of a split, the lowest
``t`` of a kept node, keeping the node before making it a leaf. A table entry holds the
value of the choice made (not the minimum), so the DP's ``R`` is the cost of the tree it
emits (and within ``(1 + tol)^depth`` of the least). Greedy collapses when
``2 a(c) >= a(n) (1 - tol)``.

Outputs
=======
:class:`CollapseResult` holds both forms the paper describes:

* ``tree``: a :class:`~jaxbvh.tree.layout.WideBVH` with ``child`` [N, K], on the *same node
  ids and capacity* as the input: removed nodes become inert padding, kept nodes keep
  their boxes and leaves their primitive runs; a node's children are listed left to
  right (the binary tree's order). :func:`jaxbvh.tree.validate` accepts it and
  :func:`jaxbvh.save` writes it compacted.
* ``skip`` [N] bool (section 4.3's fixed-width form): the binary tree kept as it is,
  with the removed nodes flagged "do not test this box, assume it is hit";
  :func:`jaxbvh.rays.traversal.trace` honours it (``skip=``) and then makes exactly the box
  tests of ``tree``, ray by ray, for all-hits queries.

The machinery sits beside this module: :mod:`jaxbvh.wide.collapse_layout` (from the
kept nodes to the wide tree: areas, level schedule, anchors and slots, emission,
prices, shared by the three methods) and :mod:`jaxbvh.wide.collapse_dp` (the optimal
collapse's tables and back-tracking).
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.configs import Checked, config_or_options, integer, knob, optional, real
from jaxbvh.numerics import min_gain, take
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import BVH, WideBVH, to_jax
from jaxbvh.wide import collapse_dp
from jaxbvh.wide import levels as lv
from jaxbvh.wide.box_tests import cost_table, node_test_cost  # noqa: F401 (public here)
from jaxbvh.wide.collapse_layout import emit, layout, links, prices, relative_areas, schedule

METHODS = ("greedy", "dp", "qbvh")
DEFAULT_MAX_CHILDREN = 8  # the DP's K when none is given (the paper used 15)
MAX_CHILDREN_LIMIT = 32  # the DP's step is unrolled over K^2 / 2 pairs (compile time)


def _method(name, value):
    if value not in METHODS:
        raise ValueError(f"unknown collapse method {value!r}; choose one of {', '.join(METHODS)}")
    return value


def _width(name, value):
    return _check_k(value, name)


_MAX_LEAF = integer(1)  # the rule for max_leaf, here and in optimal()
_CI = real(0)


@dataclasses.dataclass(frozen=True)
class CollapseConfig(Checked):
    """Knobs of a collapse (Susano Pinto 2010; module docstring, Methods).

    ``method``: ``"dp"`` (the optimal collapse, Algorithm 3), ``"greedy"`` (the top-down
    pushup, Algorithm 2) or ``"qbvh"`` (the 4-wide baseline). ``max_children``: ``K`` in
    [2, 32], the most children of a node; None: :data:`DEFAULT_MAX_CHILDREN` for dp, no
    limit for greedy (qbvh is 4-wide: None or 4). ``test_cost``: ``T(k)``, the cost of
    testing ``k`` child boxes (None: ``k``; :func:`node_test_cost`). ``max_leaf``, ``ci``
    (dp only, beyond the paper): merge subtrees of up to ``max_leaf`` primitives into one
    leaf, priced ``ci`` per primitive (:func:`optimal`).
    """

    method: str = knob("dp", check=_method, choices=METHODS,
                       help="dp: optimal collapse; greedy: top-down pushup; qbvh: 4-wide baseline")
    max_children: int | None = knob(None, check=optional(_width), type=int, metavar="K",
                                    help=f"most children per node, 2..{MAX_CHILDREN_LIMIT} (None: "
                                         f"{DEFAULT_MAX_CHILDREN} for dp, no limit for greedy; qbvh is 4-wide)")
    test_cost: Any = knob(None, help="T(k): the cost of testing k child boxes (None: k)")
    max_leaf: int = knob(1, check=_MAX_LEAF, metavar="P", help="dp only: merge subtrees of up to P "
                         "primitives into one leaf")
    ci: float = knob(1.0, check=_CI, help="cost of a primitive test, when leaves are merged")

    def _check_together(self):
        if self.max_leaf > 1 and self.method != "dp":
            raise ValueError(f"max_leaf > 1 (merging leaves) needs method 'dp', not {self.method!r}")
        if self.method == "qbvh" and self.max_children not in (None, 4):
            raise ValueError(f"qbvh is 4-wide by construction; max_children {self.max_children} does not apply")

    @property
    def widest(self) -> int | None:
        """The most children a node of the result may have (None: no limit)."""
        if self.method == "qbvh":
            return 4
        if self.method == "dp" and self.max_children is None:
            return DEFAULT_MAX_CHILDREN
        return self.max_children


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CollapseResult:
    """What a collapse returns (see the module docstring, "Outputs").

    ``tree``: the :class:`~jaxbvh.tree.layout.WideBVH`; ``kept`` [N] bool: input nodes still in
    it (root, kept interior nodes, leaves); ``skip`` [N] bool: the section 4.3 flags for
    the binary input (None when leaves were merged, which flags cannot express);
    ``rcost`` / ``rcost_before``: ``R`` of the output / input under the ``T`` used;
    ``leaf_cost`` / ``leaf_cost_before``: ``Ci sum a(leaf) count``; ``objective``: the
    DP's own ``g(root, 1)`` (:func:`optimal` only, else None).
    """

    tree: Any
    kept: Any
    skip: Any
    rcost: Any
    rcost_before: Any
    leaf_cost: Any
    leaf_cost_before: Any
    objective: Any = None


# ----------------------------------------------------------------------------------
# Costs of any tree
# ----------------------------------------------------------------------------------


@stored_jit
def _rcost(child, lo, hi, prim_count, root, table, ci):
    return prices(relative_areas(lo, hi, root), child, prim_count, table, jnp.asarray(ci, lo.dtype))


def rcost(tree, test_cost: Callable | None = None):
    """Pinto's ``R`` of a binary or wide tree under ``T = test_cost`` (default ``T(k) = k``).

    A scalar in the tree's float dtype (module docstring; the root's own test is not
    counted, leaves add nothing).
    """
    t = to_jax(tree)
    table = cost_table(test_cost, int(t.child.shape[1]))
    return _rcost(t.child, t.lo, t.hi, t.prim_count, t.root, table, 1.0)[0]


def leaf_cost(tree, ci: float = 1.0):
    """Primitive tests ``Ci * sum over leaves of a(leaf) * count(leaf)``."""
    t = to_jax(tree)
    table = np.zeros(int(t.child.shape[1]) + 1)
    return _rcost(t.child, t.lo, t.hi, t.prim_count, t.root, table, ci)[1]


# ----------------------------------------------------------------------------------
# Shared pieces (the rest is in jaxbvh.wide.collapse_layout)
# ----------------------------------------------------------------------------------


def finish(tree, kept, anchor, slot, arity, table, *, leaf_count=None, leaf_start=None,
            prim_index=None, merged=False, ci=1.0, objective=None):
    """The :class:`CollapseResult` of the nodes ``kept`` at their anchors and slots."""
    t = tree
    wide, (after, leaves_after), (before, leaves_before) = emit(
        t, kept, anchor, slot, t.prim_count if leaf_count is None else leaf_count,
        t.prim_start if leaf_start is None else leaf_start,
        t.prim_index if prim_index is None else prim_index, table, ci, arity=arity)
    # on the host: as three eager JAX ops it compiled three tiny programs on a first call
    # (~0.3 s of XLA each, issue 38)
    skip = None if merged else jnp.asarray((np.asarray(t.left) >= 0) & ~np.asarray(kept))
    return CollapseResult(tree=wide, kept=kept, skip=skip, rcost=after, rcost_before=before,
                          leaf_cost=leaves_after, leaf_cost_before=leaves_before, objective=objective)


def _binary_input(tree) -> BVH:
    if isinstance(tree, WideBVH) or not hasattr(tree, "left"):
        k = np.asarray(tree.child).shape[1] if hasattr(tree, "child") else "?"
        raise ValueError(f"collapsing needs a binary tree (BVH), got a {k}-wide tree")
    return to_jax(tree)


def _check_k(max_children, what="max_children") -> int:
    return integer(2, MAX_CHILDREN_LIMIT)(what, max_children)


# ----------------------------------------------------------------------------------
# QBVH and greedy pushup
# ----------------------------------------------------------------------------------


@stored_jit
def _qbvh_decide(tree, levels):
    _, _, interior, real = links(tree)
    return real & ~(interior & (lv.depth_of(levels) % 2 == 1))


def qbvh(tree, test_cost: Callable | None = None) -> CollapseResult:
    """The paper's QBVH baseline: remove every interior node at odd depth (4-wide)."""
    t = _binary_input(tree)
    levels = schedule(t)
    kept = _qbvh_decide(t, levels)
    anchor, slot, _ = layout(t, levels, kept)
    return finish(t, kept, anchor, slot, 4, cost_table(test_cost, 4))


@partial(stored_jit, static_argnames=("max_children",))
def _greedy_decide(tree, levels, *, max_children):
    """The kept nodes [N] bool of the greedy pushup."""
    n = tree.left.shape[0]
    left, right, interior, real = links(tree)
    a = relative_areas(tree.lo, tree.hi, tree.root)
    one = jnp.asarray(1 - min_gain(a.dtype), a.dtype)

    def collapsible(c, a_anchor):
        return take(interior, c, False) & (2 * take(a, c, 0) >= a_anchor * one)

    if max_children is None:
        def step(state, start, valid):
            kept, anchor = state
            x = levels.window(start, valid)
            xs = jnp.minimum(x, n - 1)
            owner = jnp.where(kept[xs], xs, anchor[xs])
            for c in (jnp.where(x < n, left[xs], n), jnp.where(x < n, right[xs], n)):
                kept = kept.at[c].set(~collapsible(c, a[owner]), mode="drop")
                anchor = anchor.at[c].set(owner, mode="drop")
            return kept, anchor

        kept, _ = lv.sweep_down(levels, step, (real, jnp.full(n, -1, jnp.int32)))
    else:
        k = max_children
        q_len = 2 * k - 2  # pops of one pushup: 2 + 2 per collapse, at most k - 2 collapses

        def step(kept, start, valid):
            x = levels.window(start, valid)
            xs = jnp.minimum(x, n - 1)
            w = x.shape[0]
            active = (x < n) & kept[xs]
            a_n = a[xs]
            rows = jnp.arange(w)
            queue = jnp.full((w, q_len), n, jnp.int32)
            queue = queue.at[:, 0].set(jnp.where(active, left[xs], n))
            queue = queue.at[:, 1].set(jnp.where(active, right[xs], n))
            tail = jnp.where(active, 2, 0)

            def pop(i, s):
                queue, head, tail, kids, removed = s
                live = head < tail
                c = queue[rows, jnp.minimum(head, q_len - 1)]
                width = kids + tail - head  # children of n if c stays (c counted)
                pull = live & collapsible(c, a_n) & (width + 1 <= k)
                at = jnp.where(pull, tail, q_len)
                queue = queue.at[rows, at].set(take(left, c, n), mode="drop")
                queue = queue.at[rows, at + 1].set(take(right, c, n), mode="drop")
                removed = removed.at[:, i].set(jnp.where(pull, c, n))
                return (queue, head + live, tail + 2 * pull, kids + (live & ~pull), removed)

            state = (queue, jnp.zeros(w, jnp.int32), tail, jnp.zeros(w, jnp.int32),
                     jnp.full((w, q_len), n, jnp.int32))
            removed = jax.lax.fori_loop(0, q_len, pop, state)[4]
            return kept.at[removed.reshape(-1)].set(False, mode="drop")

        kept = lv.sweep_down(levels, step, real)
    return kept


def greedy(tree, *, max_children: int | None = None, test_cost: Callable | None = None) -> CollapseResult:
    """Pinto's greedy top-down pushup (Algorithm 2); see the module docstring.

    ``max_children``: None (the paper: no limit; ``child`` is then [N, k] with ``k`` the
    widest node's children rounded up to 4 or a multiple of 8) or ``K`` in [2, 32].
    ``test_cost`` only prices the result (``rcost``).
    """
    t = _binary_input(tree)
    k = None if max_children is None else _check_k(max_children)
    levels = schedule(t)
    kept = _greedy_decide(t, levels, max_children=k)
    anchor, slot, width = layout(t, levels, kept)
    # no limit: as wide as the widest node, rounded up to 4 or a multiple of 8 (fewer compiles)
    arity = k if k is not None else (4 if int(width) <= 4 else -(-int(width) // 8) * 8)
    return finish(t, kept, anchor, slot, arity, cost_table(test_cost, arity))


# ----------------------------------------------------------------------------------
# The optimal collapse (dynamic programming: jaxbvh.wide.collapse_dp)
# ----------------------------------------------------------------------------------


def optimal(tree, *, max_children: int = DEFAULT_MAX_CHILDREN, test_cost: Callable | None = None,
            max_leaf: int = 1, ci: float = 1.0) -> CollapseResult:
    """The least-``R`` collapse (Pinto's Algorithm 3, solved level by level).

    ``max_children``: ``K`` in [2, 32], the most children of a node (MAX_CHILDS).
    ``test_cost``: ``T`` (default ``T(k) = k``; see :func:`node_test_cost`).
    ``max_leaf`` (beyond the paper): with ``P > 1`` the DP may also turn a subtree of at
    most ``P`` primitives into one leaf, at cost ``Ci a(n) count``, and then minimises
    ``R + leaf_cost`` (leaves the input already has stay as they are).
    """
    t = _binary_input(tree)
    k = _check_k(max_children)
    max_leaf, ci = _MAX_LEAF("max_leaf", max_leaf), _CI("ci", ci)
    table = cost_table(test_cost, k)
    merge = int(max_leaf) > 1
    kept, anchor, slot, objective, made_leaf, owner, count = collapse_dp.decide(
        t, schedule(t), table, ci, jnp.int32(max_leaf), max_children=k, merge=merge)
    extra = {}
    if merge:
        start, prim_index = collapse_dp.regroup_prims(t, owner, count)
        extra = dict(leaf_count=count, leaf_start=start, prim_index=prim_index, merged=True)
    return finish(t, kept, anchor, slot, k, table, ci=ci, objective=objective, **extra)


def collapse(tree, method: str | CollapseConfig = "dp", **options) -> CollapseResult:
    """One entry for the three methods (:data:`METHODS`): ``"greedy"``, ``"dp"``, ``"qbvh"``.

    ``method``: a :class:`CollapseConfig`, or a method name with the Config's other
    knobs as keywords (``max_children``, ``test_cost``, ``max_leaf``, ``ci``).
    ``max_children`` None means: no limit for greedy, 8 for dp; qbvh is 4-wide by
    construction (any other value is an error). ``max_leaf`` > 1 needs ``"dp"``.
    """
    config = (config_or_options(method, options, CollapseConfig) if isinstance(method, CollapseConfig)
              else CollapseConfig(method=method, **options))
    if config.method == "greedy":
        return greedy(tree, max_children=config.max_children, test_cost=config.test_cost)
    if config.method == "qbvh":
        return qbvh(tree, test_cost=config.test_cost)
    return optimal(tree, max_children=config.widest, test_cost=config.test_cost, max_leaf=config.max_leaf,
                   ci=config.ci)
