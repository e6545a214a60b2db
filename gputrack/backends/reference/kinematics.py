"""NumPy reference of forward kinematics (paper 000, eq. 2-11): the oracle for the other backends."""

from __future__ import annotations

import numpy as np

from ...models.chain import joint_transform


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Product of rigid transforms [Ra|ta] [Rb|tb] = [Ra Rb | Ra tb + ta], batched (..., 3, 4)."""
    r = a[..., :3] @ b[..., :3]
    t = a[..., :3] @ b[..., 3:] + a[..., 3:]
    return np.concatenate([r, t], axis=-1)


def forward_kinematics(device, chain, params, out=None):
    """(B, J, 3, 4) camera-from-part transforms, computed in float64 and returned in params' dtype
    (written into ``out`` when given)."""
    p = np.asarray(params, dtype=np.float64)
    t = np.empty((p.shape[0], chain.n_parts, 3, 4), dtype=np.float64)
    for j, part in enumerate(chain.parts):
        d = joint_transform(part, p)  # eq. 6 (root), eq. 10 (shoulder), eq. 11 (elbow)
        if part.parent < 0:
            t[:, j] = d  # eq. 4: camera-from-root is the root's pose D
        else:
            t[:, j] = compose(t[:, part.parent], d)  # eq. 2-3: D D_OU, D D_OU D_UL
    if out is None:
        return t.astype(np.asarray(params).dtype, copy=False)
    out[...] = t
    return out
