"""Sequential NumPy references: each JAX module's twin, written the slow, literal way.

They exist to be read against the papers and to hold the JAX code equal in tests; they
are not meant to be fast.
"""
