"""What ops and their kernels agree on: status codes and packed layouts.

The one source of every number that crosses the line between an op (gputrack/ops) and its
kernels (gputrack/backends, kernels/*.cl): the per-track Kalman status, the LM status and stop
reason, the slots of the LM solver's packed arrays, and the clamps every backend applies to
extreme finite inputs (INTENSITY_MAX, ANGLE_MAX). The ops import these (and re-export
:class:`KalmanStatus` and :class:`LMStatus`); the NumPy and Taichi backends read them as Python
constants (Taichi folds them into the kernels at compile time); the OpenCL sources get them as
``-D`` build defines from :func:`cl_defines` (``GT_KF_UPDATED``, ``GT_LM_S_DEN`` ...), which
``gputrack.backends.opencl.program`` passes to every build: the ``.cl`` files hold no copy and
refuse to build without them (``#error``).

This module imports nothing of gputrack: it sits below ops and backends.
"""

from __future__ import annotations

import enum

__all__ = ["ANGLE_MAX", "INTENSITY_MAX", "KalmanStatus", "LMLayout", "LMReason", "LMScale", "LMStatus", "cl_defines"]

#: the RGB-D cost (gputrack/ops/template.py) clamps every gray pixel it reads to
#: [-INTENSITY_MAX, INTENSITY_MAX] (NaN stays NaN), on every backend and in the reference: eq. 17's
#: float32 sums over N points of T_i I_i and T_i^2 (templates' values are limited to the same
#: range) then cannot overflow, and the cost, which beta makes invariant to the image's scale, is
#: the same as for the unclamped image whenever no pixel exceeds the limit. 2**48 (2.8e14).
INTENSITY_MAX = 1 << 48
#: forward kinematics clamps every finite joint angle to [-ANGLE_MAX, ANGLE_MAX] rad before sin and
#: cos, on every backend and in the reference (non-finite angles stay non-finite): float32 sine
#: and cosine keep their accuracy up to there (the Taichi kernels' argument reduction is exact for
#: |a| < 2**15 pi / 2), and an angle of thousands of turns is no pose. 2**15 = 32768 rad.
ANGLE_MAX = 1 << 15


class LMScale(enum.IntEnum):
    """The LM damping's scaling D (the global G_SCALE of the solver's state): C I, Marquardt's
    C diag(J^T J), or C times MINPACK's running maximum of diag(J^T J)."""

    IDENTITY = 0
    MARQUARDT = 1
    MINPACK = 2


class KalmanStatus(enum.IntEnum):
    """Per-track outcome of a Kalman update (the ``status`` array holds these values as uint8)."""

    UPDATED = 0
    SKIPPED = 1  # mask False, or a non-finite observation (treated as missing)
    NOT_PD = 2  # innovation covariance not positive definite: track left unchanged
    BAD_DEPTH = 3  # stereo EKF: predicted depth z <= 0: track left unchanged


class LMStatus(enum.IntEnum):
    """Per-problem outcome of :func:`gputrack.least_squares` (``RUNNING`` only appears internally)."""

    RUNNING = 0
    CONVERGED = 1
    MAX_ITER = 2
    FAILED = 3


class LMReason(enum.IntEnum):
    """Why an LM problem stopped (``LeastSquaresResult.reason``; the words: ``gputrack.ops.lm.REASONS``)."""

    RUNNING = 0
    FTOL = 1
    XTOL = 2
    GTOL = 3
    MAX_ITER = 4
    NONFINITE = 5
    NOT_PD = 6
    DAMPING = 7


class LMLayout:
    """Slots of the LM solver's packed arrays (``gputrack.ops.lm.Layout`` turns them into offsets
    for a batch of B problems with P parameters and M residuals; its docstring describes each array).

    S (solver dtype), per problem a block of ``S_NVEC * P + NSCAL`` values: the vectors of P values
    at ``slot * P`` (S_X accepted point, S_XT trial point, S_G = J^T r, S_DEN finite-difference
    denominators, S_LO / S_HI bounds, S_H absolute steps), then the scalars at ``S_NVEC * P + slot``
    (SC_F cost, SC_C damping, SC_NU damping growth, SC_PRED predicted reduction, SC_FT trial cost,
    SC_SNORM step norm). After the B blocks the NGLOB globals (G_FTOL ... G_CMAX; G_SCALE the
    damping's scaling: 0 C I, 1 Marquardt's C diag(J^T J), 2 MINPACK's running maximum of it), then
    the Jacobian mask (M * P) when there is one. The finite-difference scheme is not stored: the
    kernels tell it from the rows per problem of the residual call (2P + 1 central, P + 1 forward,
    1 none).

    K (solver dtype, uploaded): per problem ``K_NVEC * P + 1`` values: lo[P] (K_LO), hi[P] (K_HI),
    then the initial damping at ``K_NVEC * P``; then h[P]; then the NGLOB globals; then the mask.

    W (solver dtype), per problem ``W_NSQ * P * P + P * M + P`` values: J^T J (W_A) and its Cholesky
    factor (W_L) at ``slot * P * P``, then J^T (P rows of M) at ``W_NSQ * P * P``, then the P values
    of D, the damping's scale of the last step (1 for C I), at ``W_NSQ * P * P + P * M``. With a
    Jacobian callable the kernels may form J^T J and J^T r at the trial straight from the given J
    into the W_L block and the first P values of J^T (moved to W_A and S_G if it is accepted)
    instead of storing J^T, and use the rest of the J^T block as scratch.

    I (int32): NIGLOB globals (IG_B batch size, IG_HAS_MASK, IG_P), then per problem ``I_NFIX + P``
    values: I_STATUS (LMStatus), I_ITER, I_ACCEPTED, I_REASON (LMReason), then P finite flags at I_FIN.

    Out (solver dtype), per problem ``P + O_N`` values: x[P], then O_F, O_C, O_STATUS, O_ITER, O_REASON
    at ``P + slot``.
    """

    S_X, S_XT, S_G, S_DEN, S_LO, S_HI, S_H = range(7)
    S_NVEC = 7
    SC_F, SC_C, SC_NU, SC_PRED, SC_FT, SC_SNORM = range(6)
    NSCAL = 8
    G_FTOL, G_XTOL, G_GTOL, G_REL, G_CTINY, G_CMAX, G_SCALE = range(7)
    NGLOB = 8
    K_LO, K_HI = range(2)
    K_NVEC = 2
    W_A, W_L = range(2)
    W_NSQ = 2
    IG_B, IG_HAS_MASK, IG_P = 1, 2, 3
    NIGLOB = 8
    I_STATUS, I_ITER, I_ACCEPTED, I_REASON = range(4)
    I_FIN = 4
    I_NFIX = 4
    O_F, O_C, O_STATUS, O_ITER, O_REASON = range(5)
    O_N = 5


def _layout_slots() -> dict[str, int]:
    return {k: v for k, v in vars(LMLayout).items() if k.isupper() and isinstance(v, int)}


def cl_defines() -> dict[str, int]:
    """Every code and slot as an OpenCL build define: ``GT_KF_<status>``, ``GT_LM_<status>``,
    ``GT_LM_R_<reason>``, ``GT_LM_<slot>``, ``GT_INTENSITY_MAX``, ``GT_ANGLE_MAX`` and ``GT_ABI = 1``
    (the sources check it)."""
    out = {"GT_ABI": 1, "GT_INTENSITY_MAX": INTENSITY_MAX, "GT_ANGLE_MAX": ANGLE_MAX}
    out.update({f"GT_KF_{s.name}": int(s) for s in KalmanStatus})
    out.update({f"GT_LM_{s.name}": int(s) for s in LMStatus})
    out.update({f"GT_LM_R_{r.name}": int(r) for r in LMReason})
    out.update({f"GT_LM_SCALE_{m.name}": int(m) for m in LMScale})
    out.update({f"GT_LM_{k}": v for k, v in _layout_slots().items()})
    return out
