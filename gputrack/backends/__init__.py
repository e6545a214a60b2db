"""One package per backend, each with a module per primitive under the same function names.

``reference`` is NumPy/SciPy (the oracle and CPU fallback), ``taichi`` holds module-level
``@ti.kernel`` code, ``opencl`` holds thin PyOpenCL launchers for the sources in ``kernels/``.
"""
