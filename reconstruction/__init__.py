"""reconstruction package.

Its numba kernels are cached per version of its sources (`kernel_cache`): set before any kernel module loads.
"""

from reconstruction import kernel_cache

kernel_cache.configure()
