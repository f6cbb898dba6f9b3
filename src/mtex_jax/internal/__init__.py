"""White-box building blocks for tests and advanced users (the one documented internal
namespace, as ``optimistix.internal``).

Nothing here is part of the stable API: these are the kernels and helpers that the public
functions are built from, exposed so that tests can check them against independent references
without importing private modules. Nothing in the package imports this module.
"""

__all__: list[str] = []
