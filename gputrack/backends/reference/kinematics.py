"""NumPy reference of forward kinematics (paper 000, eq. 2-11): the oracle for the other backends.

The math is :meth:`gputrack.models.Chain.transforms` (the host's forward kinematics, which the
renderer and the metrics use too), in float64.
"""

from __future__ import annotations

import numpy as np


def forward_kinematics(device, chain, params, out=None):
    """(B, J, 3, 4) camera-from-part transforms, computed in float64 and returned in params' dtype
    (written into ``out`` when given)."""
    t = chain.transforms(params)  # eq. 2-11
    if out is None:
        return t.astype(np.asarray(params).dtype, copy=False)
    out[...] = t
    return out
