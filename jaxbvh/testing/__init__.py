"""A property-testing kit for anyone who writes BVH code (ours, yours, or another library's).

==================  =====================================================================
module              what it holds
==================  =====================================================================
``strategies``      hypothesis strategies: triangle soups, scenes, box sets, valid trees
                    of any arity and node order, trees with one named defect (needs
                    ``hypothesis``: ``pip install jaxbvh[testing]``; import it as
                    ``from jaxbvh.testing import strategies``)
``assertions``      :func:`assert_valid_tree`, :func:`assert_same_tree`,
                    :func:`assert_costs_close`: ``AssertionError`` with a one-line message
``oracles``         brute-force hits, exact costs, optimal trees, treelets and collapses
                    by enumeration on small inputs
``trees``           the plain-NumPy construction behind the tree strategies:
                    :func:`make_tree`, :func:`random_tree`, :func:`renumber`,
                    :func:`plant_defect`
``plugin``          the pytest plugin (entry point ``jaxbvh.testing.plugin``): mesh
                    fixtures and the hypothesis profiles ``dev`` and ``ci``
==================  =====================================================================

This package and its modules import neither pytest nor hypothesis, except ``strategies``
(hypothesis) and ``plugin`` (pytest). A guide with a worked example, testing a tree that
another library wrote: ``docs/testing.md``.
"""

from jaxbvh.testing import oracles
from jaxbvh.testing.assertions import assert_costs_close, assert_same_tree, assert_valid_tree, canonical
from jaxbvh.testing.trees import DEFECTS, Built, make_tree, plant_defect, random_tree, renumber

__all__ = ["assert_valid_tree", "assert_same_tree", "assert_costs_close", "canonical", "oracles",
           "DEFECTS", "Built", "make_tree", "plant_defect", "random_tree", "renumber"]
