"""Wide trees: binary BVHs collapsed into k-ary ones (Susano Pinto 2010).

``collapse``: greedy, optimal DP and QBVH collapsing, level by level (twin:
``collapse_reference``), with ``collapse_layout`` (from kept nodes to the wide tree)
and ``collapse_dp`` (the optimal collapse's tables); ``levels``: the level-by-level
sweeps the DP runs on;
``box_tests``: the node test cost ``T(k)`` both sides price nodes with.
"""
