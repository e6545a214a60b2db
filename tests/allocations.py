"""How much host memory a rejected call allocated (tracemalloc sees NumPy's array memory)."""

import tracemalloc

import pytest


def rejects_without_allocating(error, match, fn, limit=1 << 20):
    """Assert that ``fn()`` raises ``error`` matching ``match`` and that its host allocations never
    reached ``limit`` bytes at once: validation reads the shapes first, so a wrong-shaped input (e.g.
    a broadcast view of 2**32 rows) is rejected without being copied or scanned."""
    tracemalloc.start()
    try:
        with pytest.raises(error, match=match):
            fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < limit, f"{peak} bytes allocated before the error"
