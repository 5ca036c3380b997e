"""Experiments, the closed loop, logs and the vitreoguard command line (mm, s, rad)."""
import models.compiled_cache  # noqa: F401  (first: numba's cache folder, before any compiled function)
