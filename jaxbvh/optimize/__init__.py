"""Optimizers of a built tree: one protocol, one driver, one registry, one entry point.

=================  =====================================================================
module             what it holds
=================  =====================================================================
``protocol``       the protocol every optimizer follows (``Config``, ``init``, ``step``,
                   ``result``), its state and :class:`OptimizeResult`
``driver``         the one host driver: compiled chunks of steps, ``on_step``, budgets
``rotate``         Kensler's tree rotations: hill climbing and simulated annealing
``reinsert``       parallel reinsertion (Meister & Bittner 2018)
``treelet``        treelet restructuring (Karras & Aila 2013)
``pipeline``       rounds of treelets and reinsertion, the default
``schedules``      annealing temperature schedules, optax style
=================  =====================================================================

Each optimizer's NumPy twin sits beside it as ``<module>_reference``.

:data:`OPTIMIZERS` names every optimizer (``"hc"``, ``"sa"``, ``"reinsert"``,
``"treelet"``, ``"pipeline"``): ``OPTIMIZERS[name]`` has ``.Config``, ``.init(tree,
config=None, key=None)``, ``.step(state)`` and ``.result(state)``. :func:`optimize` runs
one by name under the driver. Every method takes ``time_budget`` (seconds, compiling
apart: the clock starts after the first step) and returns the best tree so far when it
runs out; all of them only lower the SAH except annealing, which keeps its best tree.
"""

import dataclasses

from jaxbvh.optimize import pipeline, reinsert, rotate, treelet
from jaxbvh.optimize.driver import run
from jaxbvh.optimize.protocol import Optimizer, OptimizeResult, StepInfo
from jaxbvh.tree import targets

#: every optimizer by method name (the command line's ``--method``)
OPTIMIZERS: dict[str, Optimizer] = {
    "hc": rotate.HILL_CLIMB,
    "sa": rotate.ANNEAL,
    "reinsert": reinsert.REINSERT,
    "treelet": treelet.TREELET,
    "pipeline": pipeline.PIPELINE,
}


#: the method of :func:`optimize` (and of ``jaxbvh optimize``) unless told otherwise
DEFAULT_METHOD = "pipeline"


def make_config(method: str, config=None, **options):
    """The ``Config`` of ``method``: ``config`` (None: the defaults) with ``options``
    (its fields) replaced; ``ValueError`` for an unknown method or option."""
    if method not in OPTIMIZERS:
        raise ValueError(f"method must be one of {', '.join(OPTIMIZERS)}, got {method!r}")
    Config = OPTIMIZERS[method].Config
    fields = {f.name for f in Config.__dataclass_fields__.values()}
    unknown = sorted(set(options) - fields)
    if unknown:
        raise ValueError(f"unknown option(s) {', '.join(unknown)} for method {method!r}; its options "
                         f"are the fields of its Config: {', '.join(sorted(fields))}")
    if config is None:
        return Config(**options)
    if not isinstance(config, Config):
        raise ValueError(f"config for method {method!r} must be a {Config.__module__}.Config, "
                         f"got {type(config).__name__}")
    return dataclasses.replace(config, **options) if options else config


def optimize(tree, method: str = DEFAULT_METHOD, *, key=None, time_budget: float | None = None,
             on_step=None, config=None, target=None, **options) -> OptimizeResult:
    """Optimize ``tree`` with ``method`` (a name of :data:`OPTIMIZERS`); the result has
    NumPy arrays.

    ``config``: the method's ``Config`` (None: the defaults); ``options``: fields of it
    to set (e.g. ``steps=250`` for ``"sa"``, ``first_fraction=1.0`` for ``"reinsert"``,
    ``leaves=5`` for ``"treelet"``, ``reinsert=dict(max_steps=64)`` for ``"pipeline"``).
    ``key``: ``jax.random`` key for ``"sa"`` (default ``key(0)``). ``time_budget``:
    seconds (module docstring). ``on_step(info)``: called on the host after every step
    with a :class:`~jaxbvh.optimize.protocol.StepInfo` (``info.stage`` says which
    stage of the pipeline). See :func:`jaxbvh.optimize.driver.run`. ``target``: a cost
    target (a name of :data:`jaxbvh.tree.targets.TARGETS` or a Target) whose ``ct``,
    ``ci`` and ``max_leaf`` the method uses where ``options`` do not set them.
    """
    if target is not None:
        fields = set(OPTIMIZERS[method].Config.__dataclass_fields__) if method in OPTIMIZERS else set()
        chosen = targets.costs(target)
        options = {**{k: v for k, v in chosen.items() if k in fields}, **options}
    config = make_config(method, config, **options)
    return run(OPTIMIZERS[method], tree, config, key=key, time_budget=time_budget, on_step=on_step)


__all__ = ["DEFAULT_METHOD", "OPTIMIZERS", "Optimizer", "OptimizeResult", "StepInfo", "make_config", "optimize"]
