"""Taichi backend: module-level ``@ti.kernel`` code with ndarray arguments.

Taichi keeps process-global state; :mod:`.runtime` is its one owner in gputrack.
"""
