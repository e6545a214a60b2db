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


#: devices whose compiler contracts a * b + c into one fused multiply-add whatever the build asks:
#: Taichi's CUDA code generator marks every function "unsafe-fp-math", which LLVM's NVPTX backend
#: takes as leave to fuse (fast_math=False does not change it); Taichi's SPIR-V marks no operation
#: NoContraction, so a GPU's Vulkan driver may fuse too (seen on NVIDIA's, driver 580; lavapipe
#: does not). One formula can then round differently in two kernels, and a value on a
#: discontinuity (a pixel edge, a depth gate, a radius) can land on the other side of it: FLIPS
#: elements may differ by up to FLIP_SCALE x atol there.
FUSES = ("taichi:cuda",)
FUSES_ON_GPU = ("taichi:vulkan",)
FLIPS = 1e-4  # share of the elements (at least 2)
FLIP_SCALE = 50.0


def fuses(device) -> bool:
    """Whether ``device`` contracts multiply-adds (see FUSES)."""
    return device.spec in FUSES or (device.spec in FUSES_ON_GPU and device.info.kind == "gpu")


def assert_close(device, got, want, atol: float, rtol: float = 0.0, err_msg: str = ""):
    """assert_allclose(got, want, rtol, atol), allowing FLIPS on a device that fuses (see FUSES)."""
    got, want = np.asarray(got), np.asarray(want)
    if fuses(device):
        off = ~np.isclose(got, want, rtol=rtol, atol=atol, equal_nan=True)
        if 0 < off.sum() <= max(2, FLIPS * off.size):
            np.testing.assert_allclose(got[off], want[off], rtol=rtol, atol=FLIP_SCALE * atol, err_msg=err_msg)
            return
    np.testing.assert_allclose(got, want, rtol=rtol, atol=atol, err_msg=err_msg)


def tolerance(device, dtype=np.float32, scale: float = 1.0) -> tuple[float, float]:
    rtol, atol = TOLERANCES[(np.dtype(dtype).name, device.backend)]
    return rtol * max(scale, 1.0), atol * max(scale, 1.0)


def assert_matches(device, actual, expected, dtype=np.float32, scale: float = 1.0, err_msg: str = ""):
    """Assert that ``actual`` (NumPy or DeviceArray of ``device``) matches the reference ``expected``."""
    got = gputrack.to_numpy(actual)
    want = np.asarray(expected)
    assert got.shape == want.shape, f"shape {got.shape} != reference {want.shape}"
    rtol, atol = tolerance(device, dtype, scale)
    assert_close(device, got, want, atol, rtol, err_msg=err_msg)
