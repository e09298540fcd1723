"""Pure sensor and link error models: each takes a ``numpy.random.Generator`` and returns arrays.

Parameters are frozen dataclasses in SI units (defaults are documented with the human units they
come from); invalid values raise ``ValueError`` naming the field.
"""
