"""The random numbers of the randomized algorithms, named so that an algorithm and its
NumPy twin draw the very same ones.

Each draw is keyed by *what it decides* (a node's run of primitives, a pass and a node
id), never by the order the work happens in, so the level-synchronous JAX code and the
literal sequential twin consume identical uniforms. Keys are explicit ``jax.random``
keys; nothing here holds state.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def split_uniforms(key, trial, start, count):
    """The two uniforms (float32, [..., 2]) of trial ``trial``'s node with run ``[start, start + count)``.

    ``uniform(fold_in(fold_in(fold_in(key, trial), start), count), (2,))`` for each entry
    of the int arrays ``trial``, ``start``, ``count`` (equal shapes); ``key``: the run's
    ``jax.random`` key. Runs of two nodes of a tree are disjoint or nested, and a child's
    is shorter than its parent's, so the pair names one node whatever order the nodes are
    visited in (module docstring).
    """
    trial, start, count = (jnp.asarray(a, jnp.int32) for a in (trial, start, count))

    def one(t, s, c):
        node_key = jax.random.fold_in(jax.random.fold_in(jax.random.fold_in(key, t), s), c)
        return jax.random.uniform(node_key, (2,), jnp.float32)

    flat = jax.vmap(one)(trial.ravel(), start.ravel(), count.ravel())
    return flat.reshape(start.shape + (2,))


def annealing_draws(key, pass_index, capacity: int, dtype=jnp.float32):
    """The draws of one annealing pass: [capacity, 6] Exp(1) variates ``E = -log(xi)``
    (``xi`` uniform), row = node id, column = move.

    Kensler's test ``xi < exp(-de / T)`` is ``de < T E``: a product, exact in IEEE
    arithmetic, where a logarithm taken by the annealer and again by its twin could
    differ by an ulp (XLA's ``log`` is not NumPy's) and flip a decision at a tie.
    Kensler annealing (:mod:`jaxbvh.optimize.rotate`) and its twin take their draws from here.
    """
    return jax.random.exponential(jax.random.fold_in(key, pass_index), (capacity, 6), dtype)
