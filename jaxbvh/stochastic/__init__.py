"""Stochastic construction (Ng & Trifonov 2003).

``grasp``: randomized greedy builds (GRASP), many trials at once (twin:
``grasp_reference``); ``evolve``: a genetic algorithm over insertion orders (twin:
``evolve_reference``).
"""
