"""Batches of meshes: build, optimize, cost, trace and collapse many trees in a few compiled calls.

=================  =====================================================================
module             what it holds
=================  =====================================================================
``layout``         :class:`TreeBatch`: trees stacked in capacity groups, ``unstack()``
``plan``           capacity groups and chunks under a memory bound (:class:`BatchConfig`)
``rows``           how a call runs its rows: one after another (CPU) or vmapped (GPU)
``devices``        the batch axis split over devices (``jax.shard_map``); :func:`use_cpu_cores`
``build``          every builder over a chunk of meshes: :func:`build`
``optimize``       every optimizer over a chunk of trees: :func:`optimize`
``measure``        :func:`costs`, :func:`trace` and :func:`collapse` over a batch
``chunking``       mesh files into chunks of one capacity bucket (triangles estimated
                   from the files): :func:`jaxbvh.batch.chunking.chunk_items`
``runs``           mesh *files* to tree files, here or on Dask workers, resumable:
                   :func:`jaxbvh.batch.runs.run_files` (``jaxbvh batch --scheduler``)
=================  =====================================================================

Every per-tree result equals the single-tree call (``jaxbvh.build``,
``jaxbvh.optimize.optimize``, ...) node for node; the tests hold them equal.
"""

from jaxbvh.batch.build import BuildResult, build, mesh_boxes
from jaxbvh.batch.devices import use_cpu_cores
from jaxbvh.batch.layout import Group, TreeBatch
from jaxbvh.batch.measure import collapse, costs, trace
from jaxbvh.batch.optimize import BatchOptimizeResult, optimize
from jaxbvh.batch.plan import BatchConfig

__all__ = ["build", "optimize", "costs", "trace", "collapse", "mesh_boxes", "BuildResult",
           "BatchOptimizeResult", "TreeBatch", "Group", "BatchConfig", "use_cpu_cores"]
