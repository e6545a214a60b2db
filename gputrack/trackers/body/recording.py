"""``gputrack track body``: an RGB-D recording in, the upper body's pose per frame out (JSON lines).

The recording is laid out as the ICL-NUIM and TUM RGB-D folders are: colour (or gray) images and
depth images, each given by a glob pattern or a directory. Colour is converted to gray. Depth is
a 16-bit PNG (or a 32-bit float image) of integer units: ``depth_scale`` mm per unit (TUM RGB-D and
ICL-NUIM store 5000 units per metre, 0.2 mm per unit, the default; a depth image in mm has 1; a float
image in metres 1000); 0 means no measurement. Frames are paired in order of their names (numbers
sorted as numbers); when the two folders hold different numbers of images and every name is a
time stamp (TUM RGB-D's ``1305031102.175304.png``), each RGB image is paired with the depth image
nearest in time, within ``max_dt`` s (as TUM's ``associate.py``), and RGB images without one are
left out.

The camera is a JSON file ``{"fx": ..., "fy": ..., "cx": ..., "cy": ...}`` (px), optionally with
``"width"``, ``"height"`` (checked against the images) and ``"depth_scale"`` (mm per depth unit, the
default for ``--depth-scale``); or Open3D's ``{"width", "height", "intrinsic_matrix": [9 numbers,
column-major]}`` (the form of ``camera_primesense.json``).

The start is the first frame's pose, a JSON file ``{"params": [...]}``: 14 numbers in the order of
:func:`gputrack.models.upper_body` (torso angles th, ph, ps in radians, torso position in mm, then
the arms' angles in radians), or 20 with the shoulder positions t_RS, t_LS (mm, torso coordinates),
which are then estimated too. The body model is a JSON file of the person's dimensions (mm), one
entry per part (:func:`body_model_json` writes the default)::

    {"torso": {"half_width": 160, "half_depth": 100, "top": -280, "bottom": 300},
     "shoulder": [195, -215, 0],
     "upper_arm": {"length": 290, "radius": 45},
     "forearm": {"length": 265, "radius": 38}}

Every frame is tracked, the first too (from the given pose). Each output line:
``{"frame": k, "rgb": name, "depth": name, "params": [P], "cost": c or null, "confidence": c}``
(confidence 0 and a ``"message"``: the frame could not be measured and the last pose, or with
``rigid`` the last motion, was kept); a
last line ``{"frames": N, "names": [P parameter names], "kept": n}`` (n frames kept the last pose).

``rigid=True`` tracks the camera instead (the rigid case of sec. 2.3, :func:`frame_template`): the
template comes from the previous frame's RGB-D image, and each line's ``params`` are the 6
parameters (th, ph, ps in radians; t in mm) of the motion from the previous frame's camera to this
one's, ``"pose"`` the 4x4 pose of this frame's camera in the first camera's coordinates (mm); the
first frame's motion is the identity and no pose file is needed (one with 6 numbers starts the
first motion's search).

Bad input raises FileNotFoundError / ValueError naming the file and what was expected: a missing
or unreadable frame, frames of mixed sizes, depth that reads as metres rather than the unit given,
a model file without one of the parts, a start pose of the wrong length or out of view.
"""

from __future__ import annotations

import glob
import json
import math
import os

import numpy as np

from ...models.camera import DEFAULT_CAMERA, Camera
from ...models.upper_body import DIMENSIONS, upper_body
from ..camera_file import read_camera_json
from ..image_files import frames as read_frames

__all__ = [
    "DEPTH_SCALE",
    "body_model_json",
    "check_depth_unit",
    "pair_frames",
    "read_body_model",
    "read_camera",
    "read_depth",
    "read_gray",
    "read_pose",
    "track_recording",
]

#: mm per depth unit of TUM RGB-D and ICL-NUIM's 16-bit PNGs (5000 units per metre)
DEPTH_SCALE = 0.2
#: the median measured depth of a frame must lie within these (mm): a person or a room seen by an RGB-D camera
DEPTH_RANGE_MM = (50.0, 30000.0)

#: the model file's parts: entry -> {field: DIMENSIONS key} (the shoulder: the left one, x y z; the right mirrors x)
MODEL_PARTS = {
    "torso": {"half_width": "torso_half_width", "half_depth": "torso_half_depth", "top": "torso_top",
              "bottom": "torso_bottom"},
    "shoulder": "shoulder",
    "upper_arm": {"length": "upper_arm_length", "radius": "upper_arm_radius"},
    "forearm": {"length": "forearm_length", "radius": "forearm_radius"},
}  # fmt: skip


# -- the files beside the images ----------------------------------------------------------------------
def read_camera(path: str) -> tuple[Camera, dict]:
    """(Camera, extras) from a camera file (see the module docstring); ``extras`` holds ``width``,
    ``height`` and ``depth_scale`` where the file gives them."""
    data = read_camera_json(path, ())
    extras = {}
    try:
        if "intrinsic_matrix" in data:  # Open3D's PinholeCameraIntrinsic, column-major
            k = np.asarray(data["intrinsic_matrix"], dtype=np.float64)
            if k.shape != (9,):
                raise ValueError(f'expected "intrinsic_matrix" as 9 numbers (3 x 3, column-major), got shape {k.shape}')
            k = k.reshape(3, 3).T
            cam = Camera(k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        else:
            missing = [n for n in ("fx", "fy", "cx", "cy") if n not in data]
            if missing:
                raise ValueError(
                    f'expected the keys fx, fy, cx, cy (px) or "intrinsic_matrix", missing {", ".join(missing)}'
                )
            cam = Camera(*(data[n] for n in ("fx", "fy", "cx", "cy")))
        for name in ("width", "height"):
            if name in data:
                v = data[name]
                if isinstance(v, bool) or not isinstance(v, int) or v < 2:
                    raise ValueError(f'expected "{name}" as an integer >= 2 (px), got {v!r}')
                extras[name] = v
        if "depth_scale" in data:
            extras["depth_scale"] = _positive(data["depth_scale"], '"depth_scale" (mm per depth unit)')
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: {e}") from None
    return cam, extras


def _positive(v, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"expected {what} as a finite number > 0, got {v!r}")
    return float(v)


def body_model_json(dimensions: dict | None = None) -> dict:
    """The body model file's content for ``dimensions`` (:data:`gputrack.models.upper_body.DIMENSIONS`
    keys; default: those)."""
    d = dict(DIMENSIONS, **(dimensions or {}))
    out = {}
    for part, fields in MODEL_PARTS.items():
        out[part] = (
            [float(v) for v in d[fields]] if isinstance(fields, str) else {f: float(d[k]) for f, k in fields.items()}
        )
    return out


def read_body_model(path: str) -> dict:
    """The dimensions (DIMENSIONS keys, mm) in a body model file (see the module docstring); ValueError
    naming the file and the part or field that is missing or wrong."""
    data = read_camera_json(path, (), "body model file")
    missing = [p for p in MODEL_PARTS if p not in data]
    if missing:
        raise ValueError(f"{path}: expected the parts {', '.join(MODEL_PARTS)}, missing {', '.join(missing)}")
    unknown = sorted(set(data) - set(MODEL_PARTS))
    if unknown:
        raise ValueError(f"{path}: expected only the parts {', '.join(MODEL_PARTS)}, got also {', '.join(unknown)}")
    dims = {}
    for part, fields in MODEL_PARTS.items():
        entry = data[part]
        if isinstance(fields, str):  # the shoulder: x, y, z
            ok = isinstance(entry, list) and len(entry) == 3
            if not ok or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in entry
            ):
                raise ValueError(f'{path}: expected "{part}" as [x, y, z] (mm, finite), got {entry!r}')
            dims[fields] = tuple(float(v) for v in entry)
            continue
        want = ", ".join(fields)
        if not isinstance(entry, dict):
            raise ValueError(f'{path}: expected "{part}" as an object with {want} (mm), got {entry!r}')
        gone = [f for f in fields if f not in entry]
        if gone:
            raise ValueError(f'{path}: expected "{part}" with {want} (mm), missing {", ".join(gone)}')
        for f, key in fields.items():
            v = entry[f]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f'{path}: expected "{part}".{f} as a finite number (mm), got {v!r}')
            if f in ("half_width", "half_depth", "length", "radius") and v <= 0:
                raise ValueError(f'{path}: expected "{part}".{f} > 0 (mm), got {v!r}')
            dims[key] = float(v)
    if not dims["torso_top"] < dims["torso_bottom"]:
        raise ValueError(f"{path}: expected \"torso\".top < bottom (torso y, down is +), got top {dims['torso_top']} "
                         f"and bottom {dims['torso_bottom']}")  # fmt: skip
    return dims


def read_pose(path: str, sizes: tuple) -> np.ndarray:
    """The start pose ``{"params": [...]}`` of a pose file as float64 (P,), P one of ``sizes``."""
    data = read_camera_json(path, ("params",), "pose file")
    want = " or ".join(str(n) for n in sizes)
    try:
        p = np.asarray(data["params"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f'{path}: expected "params" as a list of {want} numbers') from None
    if p.ndim != 1 or p.shape[0] not in sizes:
        raise ValueError(f'{path}: expected "params" as a list of {want} numbers, got shape {p.shape}')
    if not np.isfinite(p).all():
        raise ValueError(f'{path}: expected finite "params", got NaN or inf at index {int(np.argmin(np.isfinite(p)))}')
    return p


# -- the images ----------------------------------------------------------------------------------------
def _stem(name: str) -> str:
    return os.path.splitext(os.path.basename(name))[0]


def _number(name: str):
    """The file's stem as a number (frame number or time stamp), or None."""
    try:
        v = float(_stem(name))
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def _frame_number(name: str):
    """The file's stem as a frame number (digits only: ``00042.png``, ``42.png``), or None."""
    stem = _stem(name)
    return int(stem) if stem.isdigit() else None


def _names(path: str, what: str) -> list:
    names = sorted(glob.glob(os.path.join(path, "*"))) if os.path.isdir(path) else sorted(glob.glob(path))
    names = [n for n in names if os.path.isfile(n)]
    if not names:
        raise FileNotFoundError(f"{path}: expected {what} images (a directory or a glob pattern), found nothing")
    nums = [_number(n) for n in names]
    if None not in nums:  # frame numbers or time stamps: in their order (0.png, 1.png, ..., 10.png)
        names = [n for _, n in sorted(zip(nums, names))]
    return names


def _gap(names: list, what: str) -> None:
    """A frame missing from numbered names (0, 1, 3: 2 is missing) raises ValueError."""
    nums = [_frame_number(n) for n in names]
    if len(nums) < 3 or None in nums:
        return
    steps = np.diff(np.asarray(nums, dtype=np.int64))
    step = int(steps.min())
    if step > 0 and (steps != step).any():
        i = int(np.argmax(steps != step))
        raise ValueError(f"{names[i + 1]}: missing {what} frame {nums[i] + step} (expected frame numbers in "
                         f"steps of {step}, got {nums[i]} then {nums[i + 1]})")  # fmt: skip


def pair_frames(rgb: str, depth: str, *, max_dt: float = 0.02) -> tuple[list, int]:
    """([(rgb name, depth name), ...], RGB images left out) of a recording (see the module docstring)."""
    rn, dn = _names(rgb, "RGB"), _names(depth, "depth")
    _gap(rn, "RGB")
    _gap(dn, "depth")
    fr, fd = [_frame_number(n) for n in rn], [_frame_number(n) for n in dn]
    numbered = None not in fr and None not in fd
    if numbered and fr != fd:  # numbered frames: the same numbers on both sides
        only_r, only_d = sorted(set(fr) - set(fd)), sorted(set(fd) - set(fr))
        if only_r and (not only_d or only_r[0] < only_d[0]):
            raise ValueError(f"{depth}: missing the depth image of frame {only_r[0]} (expected the frame numbers of "
                             f"{rgb}; {len(rn)} RGB and {len(dn)} depth images)")  # fmt: skip
        raise ValueError(f"{rgb}: missing the RGB image of frame {only_d[0]} (expected the frame numbers of "
                         f"{depth}; {len(rn)} RGB and {len(dn)} depth images)")  # fmt: skip
    if len(rn) == len(dn):
        return list(zip(rn, dn)), 0
    tr, td = [_number(n) for n in rn], [_number(n) for n in dn]
    if None in tr or None in td:
        raise ValueError(f"{rgb} and {depth}: expected as many RGB as depth images (or time-stamped names to pair "
                         f"them by time), got {len(rn)} and {len(dn)}")  # fmt: skip
    td_a = np.asarray(td)
    pairs = []
    for name, t in zip(rn, tr):
        j = int(np.argmin(np.abs(td_a - t)))
        if abs(td_a[j] - t) <= max_dt:
            pairs.append((name, dn[j]))
    if not pairs:
        raise ValueError(f"{rgb} and {depth}: expected RGB and depth images within {max_dt} s of each other, "
                         f"found no pair")  # fmt: skip
    return pairs, len(rn) - len(pairs)


def read_gray(name: str) -> np.ndarray:
    """The image ``name`` as gray float32 (H, W) in [0, 1] (the shared frame reader)."""
    if not os.path.isfile(name):
        raise FileNotFoundError(f"{name}: missing RGB frame (the file is gone)")
    return next(read_frames(glob.escape(name))).astype(np.float32) / 255.0  # uint8 gray


def read_depth(name: str, depth_scale: float) -> np.ndarray:
    """The depth image ``name`` as float32 mm (H, W) (raw units times ``depth_scale``; 0 = no
    measurement): a 16-bit or float single-channel image."""
    import cv2

    if not os.path.isfile(name):
        raise FileNotFoundError(f"{name}: missing depth frame (the file is gone)")
    img = cv2.imread(name, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{name}: expected a depth image OpenCV can read, got an unreadable file")
    if img.ndim != 2:
        raise ValueError(f"{name}: expected a single-channel depth image, got {img.shape[2]} channels")
    if img.dtype not in (np.uint16, np.float32, np.float64):
        raise ValueError(f"{name}: expected a 16-bit depth image (or 32-bit float), got {img.dtype.name}")
    d = img.astype(np.float32) * np.float32(depth_scale)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def check_depth_unit(name: str, raw_median: float, depth_scale: float) -> None:
    """ValueError when a frame's median measured depth (``raw_median`` units) is not that of an RGB-D
    camera's scene in mm (:data:`DEPTH_RANGE_MM`): metres read as mm, or the wrong ``depth_scale``."""
    mm = raw_median * depth_scale
    lo, hi = DEPTH_RANGE_MM
    if lo <= mm <= hi:
        return
    if mm < lo <= mm * 1000.0 <= hi:
        raise ValueError(f"{name}: the depth looks like metres, not units of {depth_scale:g} mm (median "
                         f"{raw_median:g} units = {mm:.3g} mm): expected depth in units of --depth-scale mm "
                         f"(for an image in metres, --depth-scale 1000)")  # fmt: skip
    raise ValueError(f"{name}: expected a median depth within {lo:g}-{hi:g} mm, got {raw_median:g} units x "
                     f"{depth_scale:g} mm = {mm:.3g} mm: check --depth-scale (mm per depth unit)")  # fmt: skip


def _frame(rgb_name, depth_name, depth_scale, size) -> tuple[np.ndarray, np.ndarray]:
    """One frame's gray and depth (mm), checked: the recording's size, depth in the unit given."""
    gray = read_gray(rgb_name)
    depth = read_depth(depth_name, depth_scale)
    if size is None:
        size = (gray.shape[1], gray.shape[0])
    for name, img in ((rgb_name, gray), (depth_name, depth)):
        if img.shape != (size[1], size[0]):
            raise ValueError(f"{name}: expected a {size[0]} x {size[1]} image (the size of the recording's first "
                             f"RGB frame and the camera's), got {img.shape[1]} x {img.shape[0]}")  # fmt: skip
    valid = depth > 0
    if valid.any():
        check_depth_unit(depth_name, float(np.median(depth[valid])) / depth_scale, depth_scale)
    return gray, depth


# -- tracking ----------------------------------------------------------------------------------------------
def _check_start(path, chain, p0, camera, size) -> None:
    """The start pose must put the torso in front of the camera, in mm and in view."""
    T = chain.transforms(p0[None])[0, 0]
    x, y, z = T[:, 3]
    if z < 100.0:
        raise ValueError(f"{path}: expected the torso in front of the camera, in mm (tz_O >= 100), got "
                         f"{z:g}{' (metres?)' if 0 < z < 10 else ''}")  # fmt: skip
    u, v = camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy
    if not (0 <= u <= size[0] - 1 and 0 <= v <= size[1] - 1):
        raise ValueError(f"{path}: expected a pose with the torso in view, got its centre at pixel ({u:.0f}, {v:.0f}) "
                         f"of a {size[0]} x {size[1]} image")  # fmt: skip


def _cost(c) -> float | None:
    return float(c) if np.isfinite(c) else None


def track_recording(device, rgb: str, depth: str, out, *, camera: Camera | None = None, start=None,
                    dimensions: dict | None = None, depth_scale: float = DEPTH_SCALE, config=None,
                    rigid: bool = False, sigma=None, start_name: str = "start pose", camera_size=None,
                    save: str | None = None, every: int = 10, progress=None) -> int:  # fmt: skip
    """Track the recording ``rgb`` + ``depth`` (glob patterns or directories) and write one JSON line per
    frame to ``out`` (see the module docstring); return the number of frames.

    start: the first frame's pose (P,) (required unless ``rigid``); dimensions: the body model's
    (default: :data:`~gputrack.models.upper_body.DIMENSIONS`); config: a BodyTrackerConfig (rigid
    default: c' = 50 mm, lambda = 0.5, for the depth noise of a real sensor); sigma: the first
    particle-filter stage's sampling sigmas (rigid default: 1 deg, 10 mm); camera_size: (width, height)
    the camera file gives, checked against the images (default: the first RGB frame's); ``save``: a
    directory for a picture every ``every`` frames (not with ``rigid``); ``progress(k, line)`` per frame
    (``line``: the dict written).
    """
    from ...models import rigid as rigid_chain
    from .template import frame_template
    from .tracker import BodyTracker, BodyTrackerConfig

    depth_scale = _positive(depth_scale, "depth_scale (mm per depth unit)")
    pairs, skipped = pair_frames(rgb, depth)
    camera = camera or DEFAULT_CAMERA
    gray0, depth0 = _frame(*pairs[0], depth_scale, None if camera_size is None else tuple(camera_size))
    size = (gray0.shape[1], gray0.shape[0])
    deg = np.pi / 180.0
    if rigid:
        chain = rigid_chain()
        p0 = np.zeros(6) if start is None else np.asarray(start, dtype=np.float64)
        if p0.shape != (6,):
            raise ValueError(f"{start_name}: expected the 6 parameters of the first motion, got shape {p0.shape}")
        # the parameters are the motion from one frame to the next: starting from the last motion is
        # already a constant-velocity start (moving it by its change would extrapolate the acceleration)
        config = config or BodyTrackerConfig(c_depth=50.0, lam=0.5, predict=False)
        sigma = np.array([1 * deg, 1 * deg, 1 * deg, 10.0, 10.0, 10.0]) if sigma is None else sigma
    else:
        if start is None:
            raise ValueError("start: expected the first frame's pose (--init), got none")
        p0 = np.asarray(start, dtype=np.float64)
        if p0.shape not in ((14,), (20,)):
            raise ValueError(f"{start_name}: expected 14 parameters (or 20 with the shoulders), got shape {p0.shape}")
        chain = upper_body(shoulders=p0.shape[0] == 20, dimensions=dimensions)
        _check_start(start_name, chain, p0, camera, size)
        base = config or BodyTrackerConfig()
        if base.shoulders != (p0.shape[0] == 20):
            import dataclasses

            base = dataclasses.replace(base, shoulders=p0.shape[0] == 20)
        config = base
    trk = BodyTracker(device, p0, camera=camera, size=size, config=config, chain=chain, sigma=sigma)
    if save:
        os.makedirs(save, exist_ok=True)
    pose = np.eye(4)  # rigid: this camera in the first camera's coordinates
    previous = None
    kept = 0
    n = 0
    for k, (rgb_name, depth_name) in enumerate(pairs):
        gray, dep = (gray0, depth0) if k == 0 else _frame(rgb_name, depth_name, depth_scale, size)
        rec = {"frame": k, "rgb": os.path.basename(rgb_name), "depth": os.path.basename(depth_name)}
        if rigid:
            if previous is None:
                rec.update(params=[0.0] * 6, pose=pose.tolist(), cost=None, confidence=1.0)
            else:
                try:
                    templates, why = frame_template(*previous, camera), ""
                except ValueError as e:  # no depth in the previous frame: keep the last motion
                    templates, why = None, f"no template from the previous frame ({e})"
                if templates is None:
                    params, cost, conf, msg = trk.params.copy(), None, 0.0, why
                else:
                    est = trk.track(gray, dep, templates=templates)
                    params, cost, conf, msg = est.params, _cost(est.cost), est.confidence, est.message
                M = np.eye(4)
                M[:3] = chain.transforms(params[None])[0, 0]
                pose = pose @ np.linalg.inv(M)
                rec.update(params=params.tolist(), pose=pose.tolist(), cost=cost, confidence=conf)
                if conf == 0.0:
                    rec["message"] = msg
                    kept += 1
            previous = (gray, dep)
        else:
            est = trk.track(gray, dep)
            rec.update(params=est.params.tolist(), cost=_cost(est.cost), confidence=est.confidence)
            if est.confidence == 0.0:
                rec["message"] = est.message
                kept += 1
        out.write(json.dumps(rec) + "\n")
        if save and k % max(1, every) == 0 and not rigid:
            _picture(save, k, gray, chain, trk, camera)
        if progress is not None:
            progress(k, rec)
        n = k + 1
    out.write(json.dumps({"frames": n, "names": list(chain.param_names), "kept": kept, "left_out": skipped}) + "\n")
    return n


def _picture(save, k, gray, chain, trk, camera) -> None:
    import cv2

    from .pictures import draw_estimate

    img = draw_estimate(gray, chain, trk.params, camera, templates=trk.templates, label=f"frame {k}")
    cv2.imwrite(os.path.join(save, f"frame_{k:05d}.png"), img)
