"""The 5-part upper body of paper 000 (eq. 1, 6-11; eq. 25-27 with the shoulder positions).

Parts, in this order (parents first): torso, right upper arm, left upper arm, right forearm,
left forearm. Parameters (0-based; angles in radians, lengths in millimetres):

    0-2   th_O, ph_O, ps_O      torso rotation Rz(th) Ry(ph) Rx(ps)          (eq. 6-9)
    3-5   t_O = (x, y, z)       torso position in the camera                  (eq. 6)
    6-7   th_RU, ph_RU          right upper arm at the shoulder: Rz(th) Ry(ph) (p_RU, eq. 10)
    8-9   th_LU, ph_LU          left upper arm                                 (p_LU, eq. 10)
    10-11 th_RL, ph_RL          right forearm at the elbow: Rz(th) Ry(ph)      (p_RL, eq. 11)
    12-13 th_LL, ph_LL          left forearm                                   (p_LL, eq. 11)
    14-16 t_RS                  right shoulder position in torso coordinates  (eq. 25-27, 20-param variant)
    17-19 t_LS                  left shoulder position in torso coordinates

Coordinates. Camera: x right, y down, z forward (depth). Torso: origin at the middle of the
chest, x towards the person's left, y down, z towards the person's back; so the rest pose
(all torso angles 0) is an upright person facing the camera. Arms: origin at the joint, main
axis x along the limb (the axis of the papers' accuracy measure). With Rz(th) Ry(ph) the
limb's direction in its parent's coordinates is (cos th cos ph, sin th cos ph, -sin ph): th
swings it in the parent's x-y plane, positive ph moves it towards -z (forward, towards the
camera when the person faces it). An arm hanging straight down has th = 90 deg, ph = 0, for
either arm (the right arm is not mirrored: spread sideways it has th = 180 deg, the left 0).

The torso rotation follows eq. 6 (Rz Ry Rx; eq. 14 of the paper lists the factors in another
order for the sampled pose, which we read as the same rotation).
"""

from __future__ import annotations

import numpy as np

from .chain import Chain, Part, Shape

__all__ = ["DIMENSIONS", "PF_SIGMA", "pf_sigma", "upper_body"]

#: body dimensions in millimetres (an adult of average build)
DIMENSIONS = {
    "torso_half_width": 160.0,  # semi-axis along torso x
    "torso_half_depth": 100.0,  # semi-axis along torso z
    "torso_top": -280.0,  # torso y of the top cap (up is -y)
    "torso_bottom": 300.0,  # torso y of the bottom cap
    "shoulder": (195.0, -215.0, 0.0),  # left shoulder in torso coordinates; the right one mirrors x
    "upper_arm_length": 290.0,  # shoulder to elbow (t_E = (length, 0, 0), eq. 11)
    "upper_arm_radius": 45.0,
    "forearm_length": 265.0,  # elbow to finger tips (forearm and hand as one capsule)
    "forearm_radius": 38.0,
}

#: Table 4: the first stage's sampling standard deviations (mm, degrees)
PF_SIGMA = {
    "torso_t": (5.0, 5.0, 5.0),
    "torso_angles": (1.0, 3.0, 1.0),  # th (about z), ph (about y: turning), ps (about x)
    "shoulder": (8.0, 8.0),
    "elbow": (15.0, 15.0),
}

PARAM_NAMES = (
    "th_O", "ph_O", "ps_O", "tx_O", "ty_O", "tz_O",
    "th_RU", "ph_RU", "th_LU", "ph_LU",
    "th_RL", "ph_RL", "th_LL", "ph_LL",
)  # fmt: skip
SHOULDER_NAMES = ("x_RS", "y_RS", "z_RS", "x_LS", "y_LS", "z_LS")


def upper_body(shoulders: bool = False, dimensions: dict | None = None) -> Chain:
    """The 5-part chain with 14 parameters, or 20 with both shoulder positions as parameters.

    ``dimensions`` overrides entries of :data:`DIMENSIONS` (e.g. another person's build). With
    ``shoulders=True`` the shoulder joints' translations are parameters 14-16 (t_RS) and 17-19
    (t_LS) and their fixed offsets are zero; the rest vector holds the generic positions.
    """
    d = dict(DIMENSIONS)
    if dimensions:
        unknown = set(dimensions) - set(DIMENSIONS)
        if unknown:
            raise ValueError(f"dimensions: expected keys among {sorted(DIMENSIONS)}, got unknown {sorted(unknown)}")
        d.update(dimensions)
    lx, ly, lz = (float(v) for v in d["shoulder"])
    t_ls = (lx, ly, lz)
    t_rs = (-lx, ly, lz)
    lu, lf = float(d["upper_arm_length"]), float(d["forearm_length"])

    torso_radii = (d["torso_half_width"], d["torso_half_depth"])
    torso_shape = Shape("cylinder", 1, d["torso_top"], d["torso_bottom"], torso_radii)
    upper_shape = Shape("capsule", 0, 0.0, lu, (d["upper_arm_radius"],) * 2)
    fore_shape = Shape("capsule", 0, 0.0, lf, (d["forearm_radius"],) * 2)

    if shoulders:
        rs = dict(offset=(0.0, 0.0, 0.0), translation=(14, 15, 16))
        ls = dict(offset=(0.0, 0.0, 0.0), translation=(17, 18, 19))
    else:
        rs = dict(offset=t_rs)
        ls = dict(offset=t_ls)
    parts = (
        Part("torso", -1, "zyx", (0, 1, 2), translation=(3, 4, 5), shape=torso_shape),  # eq. 6
        Part("right_upper_arm", 0, "zy", (6, 7), shape=upper_shape, **rs),  # eq. 10 / 27
        Part("left_upper_arm", 0, "zy", (8, 9), shape=upper_shape, **ls),
        Part("right_forearm", 1, "zy", (10, 11), offset=(lu, 0.0, 0.0), shape=fore_shape),  # eq. 11
        Part("left_forearm", 2, "zy", (12, 13), offset=(lu, 0.0, 0.0), shape=fore_shape),
    )
    deg = np.pi / 180.0
    rest = [0.0, 0.0, 0.0, 0.0, 0.0, 2000.0,  # upright, facing the camera 2 m away
            105 * deg, 0.0, 75 * deg, 0.0,  # arms hanging, 15 deg away from the body
            0.0, 20 * deg, 0.0, 20 * deg]  # elbows bent 20 deg forward  # fmt: skip
    names = PARAM_NAMES
    if shoulders:
        rest += [*t_rs, *t_ls]
        names = names + SHOULDER_NAMES
    name = "upper_body_20" if shoulders else "upper_body_14"
    return Chain(parts, len(rest), names, tuple(float(v) for v in rest), name=name)


def pf_sigma(chain: Chain, shoulder_sigma_mm: float = 0.0) -> np.ndarray:
    """(P,) float64 Table 4 sampling sigmas for :func:`upper_body` chains, in parameter units.

    Angles are returned in radians. The shoulder positions of the 20-parameter variant are
    not sampled by the paper's particle filter (the LM estimates them): ``shoulder_sigma_mm``.
    """
    if chain.n_params not in (14, 20) or chain.param_names[:14] != PARAM_NAMES:
        raise ValueError(f"chain: expected an upper_body() chain, got {chain.name} with {chain.n_params} parameters")
    deg = np.pi / 180.0
    s = PF_SIGMA
    sigma = [*(a * deg for a in s["torso_angles"]), *s["torso_t"]]
    sigma += [s["shoulder"][0] * deg, s["shoulder"][1] * deg] * 2
    sigma += [s["elbow"][0] * deg, s["elbow"][1] * deg] * 2
    if chain.n_params == 20:
        sigma += [float(shoulder_sigma_mm)] * 6
    return np.asarray(sigma, dtype=np.float64)
