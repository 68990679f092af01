"""Which XLA compiler options each of jaxbvh's compiled programs gets: the one place.

On a CPU, compiling is most of a first call (issue 38). Two XLA options make it cheaper:
``xla_cpu_use_fusion_emitters=False`` (XLA's older loop emitters for fusions instead of
its MLIR fusion emitters) and ``xla_backend_optimization_level=0`` (LLVM's optimizations
off). Measured on spot (``bench/results/bench_compile_policy.md``, CPU seconds, 2 shared
cores): the old emitters cut a first call's compile by 25-45% for the builders, SBVH,
collapse, hill climbing and the ray trace (nothing for the pipeline's large loop, whose
steps then run ~20% slower), and the compiled code runs 0-37% slower (it also loads
from the persistent cache a little slower: SBVH's warm call 0.97 -> 1.35 CPU s); level 0 cuts compile by another third to a half but the
code runs 4.5-6.5 times slower, which a warm process (programs loaded from the
persistent cache, :mod:`jaxbvh.compile_cache`) pays at every call. Level 1 or 2 compile
no cheaper than XLA's default 3. So the programs are sorted into two *families* by how
long their compiled code runs:

``"once"``
    a program that runs once per call of the user's (the builders, SBVH, collapse, the
    two-level build, costs, ray generation): a first call is mostly its compile, and a
    new mesh size is a new program. Default: the old emitters.
``"loop"``
    a program whose compiled code runs long or many times over (an optimizer's loop of
    steps, a batch of rays traced, a query batch, the stochastic searches): its speed is
    what a time budget buys and what every later call pays, and its compile is paid once
    per machine. Default: XLA's own options (the fastest code).

Every top-level program of the package goes through
:func:`jaxbvh.program_store.stored_jit`, which asks :func:`options` for its family's
options at every call (so a change of policy applies at once; each option set is its
own compiled program, in memory and in JAX's persistent cache, whose key includes the
options). A program's family is ``stored_jit(..., family=...)``, else
:func:`family_of` its module (:data:`LOOP_MODULES`).

Policies (:data:`POLICIES`): ``"default"`` (the families above, :data:`DEFAULT_POLICY`),
``"xla"`` (no options anywhere: XLA's defaults, the fastest code, the dearest compile)
and ``"fast-compile"`` (both options everywhere: the cheapest compile and the slowest
code; the test suite's choice, through ``XLA_FLAGS``). Choose one with
``JAXBVH_COMPILE_POLICY=<name>`` in the environment, or in a running process with
:func:`set_policy` (a name, or a mapping ``{family: {option: value}}`` of your own).

Rules:

1. An option named in ``XLA_FLAGS`` is never set per program: the user's flags win
   (XLA applies a program's options over the flags, so setting it would override
   them). The test suite's ``XLA_FLAGS`` (``tests/helpers.py`` ``UNOPTIMIZED_XLA``) so
   stay in force for every program.
2. Programs outside a top-level :func:`stored_jit` call get no options: JAX's own eager
   operations, and a jaxbvh function called inside a user's ``jit``, ``vmap`` or
   ``grad``, which is traced into the user's program (JAX takes compiler options only
   on a top-level ``jit``).
3. The options change the compiled code, never the results' meaning: XLA keeps IEEE
   semantics under all of them, but a float reduction may be summed in another order,
   so a float sum can differ in its last bits between policies (trees do not, tested).
"""

from __future__ import annotations

import os
import types
from typing import Mapping

__all__ = ["DEFAULT_POLICY", "FAMILIES", "LOOP_MODULES", "POLICIES", "POLICY_VARIABLE", "family_of", "options",
           "policy", "set_policy"]

#: the program families (module docstring)
FAMILIES = ("once", "loop")

#: XLA's two cheap-compile options (module docstring)
_OLD_EMITTERS = types.MappingProxyType({"xla_cpu_use_fusion_emitters": False})
_CHEAP = types.MappingProxyType({"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False})

#: jaxbvh's policy: family -> XLA options (module docstring, bench/results/bench_compile_policy.md)
DEFAULT_POLICY = types.MappingProxyType({"once": _OLD_EMITTERS, "loop": types.MappingProxyType({})})

#: name -> policy
POLICIES = types.MappingProxyType({
    "default": DEFAULT_POLICY,
    "xla": types.MappingProxyType({"once": types.MappingProxyType({}), "loop": types.MappingProxyType({})}),
    "fast-compile": types.MappingProxyType({"once": _CHEAP, "loop": _CHEAP}),
})

#: the environment variable naming the policy (read when first needed)
POLICY_VARIABLE = "JAXBVH_COMPILE_POLICY"

#: modules (prefixes of ``__module__``) whose programs are of the ``"loop"`` family; every
#: other program is ``"once"``
LOOP_MODULES = ("jaxbvh.optimize.", "jaxbvh.rays.traversal", "jaxbvh.rays.measure", "jaxbvh.twolevel.traversal",
                "jaxbvh.queries.", "jaxbvh.stochastic.")

#: the policy set by set_policy (None: the environment's, else "default")
_chosen: dict = {"policy": None}


def _check(table: Mapping) -> dict:
    """``table`` as ``{family: {option: value}}`` with every family, or ValueError."""
    unknown = set(table) - set(FAMILIES)
    if unknown:
        raise ValueError(f"unknown program families {sorted(unknown)}; the families are {FAMILIES}")
    return {family: dict(table.get(family, {})) for family in FAMILIES}


def _named(name: str) -> dict:
    try:
        return _check(POLICIES[name])
    except KeyError:
        raise ValueError(f"unknown compile policy {name!r}; the policies are {', '.join(POLICIES)} "
                         f"(${POLICY_VARIABLE} or jaxbvh.compile_policy.set_policy)") from None


def policy() -> dict:
    """The policy in force: ``{family: {option: value}}`` (:func:`set_policy`'s, else
    ``$JAXBVH_COMPILE_POLICY``'s, else :data:`DEFAULT_POLICY`), before rule 1."""
    if _chosen["policy"] is not None:
        return {family: dict(opts) for family, opts in _chosen["policy"].items()}
    return _named(os.environ.get(POLICY_VARIABLE, "").strip() or "default")


def set_policy(chosen: str | Mapping | None) -> dict | None:
    """Use ``chosen`` from now on in this process: a name of :data:`POLICIES`, a mapping
    ``{family: {option: value}}`` (a family left out gets no options), or None (back to
    ``$JAXBVH_COMPILE_POLICY`` / the default). Returns the policy set before (None: none
    was set), to restore it with."""
    before = _chosen["policy"]
    if chosen is None:
        _chosen["policy"] = None
    else:
        _chosen["policy"] = _named(chosen) if isinstance(chosen, str) else _check(chosen)
    return before


def _flag_names() -> set[str]:
    """The option names in ``XLA_FLAGS`` (``--name=value`` or ``--name``)."""
    return {token.lstrip("-").split("=", 1)[0] for token in os.environ.get("XLA_FLAGS", "").split()
            if token.startswith("--")}


def options(family: str) -> dict:
    """The XLA options of a program of ``family`` under the policy in force, less those
    named in ``XLA_FLAGS`` (rule 1): a dict for ``jax.jit(..., compiler_options=...)``."""
    if family not in FAMILIES:
        raise ValueError(f"unknown program family {family!r}; the families are {FAMILIES}")
    named = _flag_names()
    return {name: value for name, value in policy()[family].items() if name not in named}


def family_of(module: str) -> str:
    """The family of a program defined in ``module`` (a ``__module__``): ``"loop"`` for
    :data:`LOOP_MODULES`, else ``"once"``."""
    return "loop" if module.startswith(LOOP_MODULES) else "once"
