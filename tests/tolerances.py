"""The one tolerance table for comparing a backend with the NumPy reference.

Keyed by (dtype, backend). ``scale`` widens a comparison for results that are sums over many
terms (documented at the call site); it never narrows below the table.
"""

import numpy as np

import gputrack

# (rtol, atol)
TOLERANCES = {
    ("float32", "numpy"): (1e-6, 1e-6),
    ("float32", "taichi"): (2e-5, 2e-5),
    ("float32", "opencl"): (2e-5, 2e-5),
    ("float64", "numpy"): (1e-12, 1e-12),
    ("float64", "taichi"): (1e-10, 1e-10),
    ("float64", "opencl"): (1e-10, 1e-10),
}


def tolerance(device, dtype=np.float32, scale: float = 1.0) -> tuple[float, float]:
    rtol, atol = TOLERANCES[(np.dtype(dtype).name, device.backend)]
    return rtol * max(scale, 1.0), atol * max(scale, 1.0)


def assert_matches(device, actual, expected, dtype=np.float32, scale: float = 1.0, err_msg: str = ""):
    """Assert that ``actual`` (NumPy or DeviceArray of ``device``) matches the reference ``expected``."""
    got = gputrack.to_numpy(actual)
    want = np.asarray(expected)
    assert got.shape == want.shape, f"shape {got.shape} != reference {want.shape}"
    rtol, atol = tolerance(device, dtype, scale)
    np.testing.assert_allclose(got, want, rtol=rtol, atol=atol, err_msg=err_msg)
