"""Stochastic construction (Ng & Trifonov 2003).

``grasp``: randomized greedy builds (GRASP), many trials at once (twin:
``grasp_reference``); ``evolve``: a genetic algorithm over insertion orders (twin:
``evolve_reference``). Both report as the optimizers do: their results are
:class:`jaxbvh.optimize.protocol.OptimizeResult` (tree, sah by their cost, steps, history,
stop, seconds, compile_seconds, trace) and ``on_step(info)`` gets a
:class:`~jaxbvh.optimize.protocol.StepInfo` after every trial or generation.
"""
