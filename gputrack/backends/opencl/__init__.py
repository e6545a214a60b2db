"""OpenCL backend: thin PyOpenCL launchers; kernel sources live in the top-level ``kernels/``."""
