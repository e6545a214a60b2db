"""Data the math runs on: cameras (pinhole, rectified stereo, depth) and kinematic chains (paper 000's
upper body, rigid single parts), with the renderer that draws a chain (:mod:`.render`)."""

from .camera import DEFAULT_CAMERA, DEFAULT_SIZE, Camera, DepthCamera, StereoCamera
from .chain import Chain, Part, Shape, joint_transform, rotation
from .upper_body import DIMENSIONS, PF_SIGMA, pf_sigma, upper_body

__all__ = [
    "Camera",
    "Chain",
    "DEFAULT_CAMERA",
    "DEFAULT_SIZE",
    "DIMENSIONS",
    "DepthCamera",
    "PF_SIGMA",
    "Part",
    "Shape",
    "StereoCamera",
    "joint_transform",
    "pf_sigma",
    "rigid",
    "rotation",
    "upper_body",
]


def rigid(shape: Shape | None = None, name: str = "rigid") -> Chain:
    """A single free part (6 parameters: Rz Ry Rx angles, then translation): a rigid object or camera."""
    part = Part(name, -1, "zyx", (0, 1, 2), translation=(3, 4, 5), shape=shape)
    return Chain((part,), 6, ("th", "ph", "ps", "tx", "ty", "tz"), (0.0,) * 6, name=name)
