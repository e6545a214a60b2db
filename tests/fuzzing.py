"""The fuzz suite's table (tests/test_fuzz.py): every public op and tracker entry point with a
small valid call, the mutations applied to its arguments, and the oracle.

The oracle: an op called on a device with a mutated argument must do what the NumPy reference does
with the same argument, either raise the same clear exception (ValueError, TypeError, MemoryError
or DeviceUnavailable, with a message saying what was expected and what was got: the same
message on every backend) or return results equal to the reference's (the tolerance table of
tests/tolerances.py). A layout-only mutation (a view, negative strides, Fortran order, a read-only
array, a list, an array already on the device) must give the clean call's results. Mutations that
only a device can have (NaN written on the device, an array of another device) must end in a
clear exception or in results of the clean call's shapes, never in a crash.

Profiles: ``GPUTRACK_FUZZ=deep`` (or ``pytest --fuzz=deep``) applies every mutation to every
argument, with several seeds; the default ("fast") applies the layout mutations to one argument
per op in turn, to keep the suite within its time budget. Cases that could crash the process or
run away with memory (outputs too large for the device, huge sizes) run in a subprocess under
``resource.setrlimit`` limits (tests/fuzz_child.py).
"""

from __future__ import annotations

import dataclasses
import os
import re
from typing import Any, Callable

import numpy as np
from conftest import deep

import gputrack
from gputrack.device import DeviceArray, DeviceUnavailable

#: the exceptions a bad argument may raise (anything else, e.g. AttributeError or IndexError, is a defect)
CLEAR = (ValueError, TypeError, MemoryError, DeviceUnavailable)

REF = gputrack.device("numpy")


def profile() -> str:
    if deep():  # the suite's deep profile
        return "deep"
    return os.environ.get("GPUTRACK_FUZZ", "fast").strip().lower() or "fast"


@dataclasses.dataclass
class Case:
    """One op's valid call: ``call(device, **args)``; ``arrays``: the names of the array arguments
    the mutations apply to; ``scalars``: {name: [bad or edge values]} for its scalar arguments;
    ``post(result)``: the result as a list of NumPy arrays to compare (default: every array in it);
    ``scale``: widens the tolerance (sums over many terms)."""

    name: str
    call: Callable
    args: dict
    arrays: tuple = ()
    scalars: dict = dataclasses.field(default_factory=dict)
    post: Callable | None = None
    scale: float = 10.0
    tracker: bool = False  # a tracker entry point: stateful, so only refusals and the clean call are compared
    nan_ok: tuple = ()  # arguments where NaN/inf are documented input (no measurement, no point): may be accepted


# -- the results as NumPy arrays ----------------------------------------------------------------------
def flatten(result) -> list:
    """Every array of a result (DeviceArray, ndarray, numbers, tuples, named tuples, dataclasses)."""
    if result is None:
        return []
    if isinstance(result, (DeviceArray, np.ndarray)):
        return [gputrack.to_numpy(result)]
    if isinstance(result, (int, float, np.integer, np.floating, bool)):
        return [np.asarray(result)]
    if dataclasses.is_dataclass(result):
        return [a for f in dataclasses.fields(result) for a in flatten(getattr(result, f.name))]
    if isinstance(result, (tuple, list)):
        return [a for r in result for a in flatten(r)]
    return []


def results(case: Case, result) -> list:
    if case.tracker:
        return []  # a frame's estimate: the trackers' own tests pin those to the reference
    return [np.asarray(a) for a in (case.post(result) if case.post else flatten(result))]


def assert_same(device, case: Case, got: list, want: list, what: str) -> None:
    from tolerances import tolerance

    assert len(got) == len(want), f"{case.name} {what}: {len(got)} results, the reference {len(want)}"
    for i, (g, w) in enumerate(zip(got, want)):
        assert g.shape == w.shape, f"{case.name} {what}: result {i} has shape {g.shape}, the reference {w.shape}"
        if w.dtype.kind in "biu" and g.dtype.kind in "biu":
            np.testing.assert_array_equal(g, w, err_msg=f"{case.name} {what}: result {i}")
            continue
        rtol, atol = tolerance(device, np.float32, case.scale)
        np.testing.assert_allclose(g.astype(np.float64), w.astype(np.float64), rtol=rtol, atol=atol,
                                   err_msg=f"{case.name} {what}: result {i}")  # fmt: skip


# -- outcomes ------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Outcome:
    error: BaseException | None = None
    value: Any = None

    def describe(self) -> str:
        return f"{type(self.error).__name__}: {self.error}" if self.error else "a result"


def run(case: Case, device, args: dict) -> Outcome:
    try:
        return Outcome(value=case.call(device, **args))
    except Exception as e:  # noqa: BLE001 - judged by the oracle
        return Outcome(error=e)


#: the message of a DeviceArray given where a host array is read (gputrack/device.py)
IMPLICIT = "a DeviceArray is not converted implicitly; call .numpy() to download it"

_SPEC = re.compile(r"(numpy|taichi:\w+|opencl(:[\w.-]+)?)")


def assert_clear(case: Case, what: str, e: BaseException) -> None:
    """A clear exception: one of CLEAR whose message says what was expected and what was got."""
    msg = str(e)
    assert isinstance(e, CLEAR), f"{case.name} {what}: unclear exception {type(e).__name__}: {msg}"
    if isinstance(e, TypeError) and msg.startswith(IMPLICIT):
        return  # the DeviceArray's own refusal to convert (gputrack/device.py): clear, by design
    if isinstance(e, (ValueError, TypeError)):
        low = msg.lower()
        assert "expected" in low and "got" in low, f"{case.name} {what}: message without expected/got: {msg!r}"
    if isinstance(e, MemoryError):
        assert "bytes" in msg, f"{case.name} {what}: a MemoryError that does not name the bytes: {msg!r}"


#: mutations no op may accept (the values would be silently converted or dropped)
MUST_REFUSE = ("complex", "object", "string", "ragged")
#: host NaN/inf: refused unless the argument documents them (Case.nan_ok): never a silent NaN result
NON_FINITE = (" nan", " inf", " -inf")


def assert_refused(case: Case, what: str, want: Outcome) -> None:
    """Complex, object, string and ragged arguments, and host NaN/inf outside ``case.nan_ok``, must
    be refused (by the reference, hence by every device, which ``judge`` holds to it)."""
    if what.endswith(MUST_REFUSE) or what.endswith(NON_FINITE) and what.rsplit(" ", 1)[0] not in case.nan_ok:
        assert want.error is not None, f"{case.name} {what}: accepted by the reference (expected a clear refusal)"


def judge(device, case: Case, what: str, got: Outcome, want: Outcome, *, clean: list | None = None) -> None:
    """The oracle: the device does what the reference does (same clear exception, or equal results);
    ``clean``: the results a layout-only mutation must give. Complex, object, string and ragged
    arguments must be refused (by the reference too)."""
    assert_refused(case, what, want)
    if want.error is not None:
        assert_clear(case, f"{what} (reference)", want.error)
        assert got.error is not None, f"{case.name} {what}: the reference raised {want.describe()}, {device.spec} returned"
        assert_clear(case, what, got.error)
        assert type(got.error) is type(want.error), (
            f"{case.name} {what}: {device.spec} raised {got.describe()}, the reference {want.describe()}"
        )
        norm = lambda e: _SPEC.sub("<device>", str(e))  # noqa: E731
        # the same message on every backend (a MemoryError names the device's own limit)
        assert isinstance(got.error, MemoryError) or norm(got.error) == norm(want.error), (
            f"{case.name} {what}: {device.spec} says {got.error!s}, the reference {want.error!s}"
        )
        return
    assert got.error is None, f"{case.name} {what}: the reference returned, {device.spec} raised {got.describe()}"
    want_r = results(case, want.value)
    assert_same(device, case, results(case, got.value), want_r, what)
    if clean is not None:
        assert_same(REF, case, want_r, clean, f"{what} (the reference against its clean call)")


# -- mutations ------------------------------------------------------------------------------------------
def _pad_last(x):
    x = np.asarray(x)
    if x.ndim == 0:
        return x[None]
    return np.concatenate([x, x[..., -1:]], axis=-1)


def _with(x, value):
    x = np.array(x, copy=True)
    if x.size and x.dtype.kind == "f":
        x.flat[x.size // 2] = value
        return x
    return None


def _view(x):
    x = np.asarray(x)
    if x.ndim == 0:
        return None
    return np.repeat(x, 2, axis=-1)[..., ::2]  # every other element of a wider array


def _negative(x):
    x = np.asarray(x)
    if x.ndim == 0:
        return None
    return np.flip(np.flip(x, 0).copy(), 0)


def _readonly(x):
    x = np.array(x, copy=True)
    x.flags.writeable = False
    return x


def _empty(x):
    x = np.asarray(x)
    return x[:0] if x.ndim else None


#: (name, kind, mutate): kind "layout" keeps the values (the clean result is owed); "value" may
#: be refused or accepted (as the reference does)
HOST_MUTATIONS = [
    ("ndim+1", "value", lambda x: np.asarray(x)[None]),
    ("ndim-1", "value", lambda x: np.asarray(x)[0] if np.ndim(x) else None),
    ("shape+1", "value", _pad_last),
    ("empty", "value", _empty),
    ("float64", "value", lambda x: np.asarray(x).astype(np.float64)),
    ("int32", "value", lambda x: np.asarray(x).astype(np.int32)),
    ("complex", "value", lambda x: np.asarray(x).astype(np.complex64)),
    ("object", "value", lambda x: np.asarray(x).astype(object)),
    ("bool", "value", lambda x: np.asarray(x).astype(bool)),
    ("nan", "value", lambda x: _with(x, np.nan)),
    ("inf", "value", lambda x: _with(x, np.inf)),
    ("-inf", "value", lambda x: _with(x, -np.inf)),
    ("None", "value", lambda x: None),
    ("string", "value", lambda x: "not an array"),
    ("ragged", "value", lambda x: [[0.0], [0.0, 1.0]]),
    ("view", "layout", _view),
    ("negative strides", "layout", _negative),
    ("fortran", "layout", lambda x: np.asfortranarray(x) if np.ndim(x) > 1 else None),
    ("read-only", "layout", _readonly),
    ("list", "layout", lambda x: np.asarray(x).tolist()),
]
LAYOUT = [m for m in HOST_MUTATIONS if m[1] == "layout"]
VALUE = [m for m in HOST_MUTATIONS if m[1] == "value"]

#: scalar mutations every scalar argument gets (besides the case's own list); integers >= 2**31
#: given to an integer argument (a count, a size, a seed) run in the limited child process
SCALARS = [None, np.nan, np.inf, -1, 0, True, "x", 1.5, 1e30, 2**70]


# -- the cases ----------------------------------------------------------------------------------------------
#: the cases' names (tests/test_fuzz.py parametrises over them without building the table)
OP_NAMES = [
    "forward_kinematics", "rgbd_cost", "rgbd_residuals", "patch_ncc", "patch_ncc_per_point", "sample_around", "best_k",
    "pf_stage", "pose_residuals", "kf_predict", "kf_update", "ekf_update_stereo", "mahalanobis",
    "kf_update singular P", "kf_update indefinite P", "gate_pairs", "normal_equations", "lm_step", "lm_solve",
    "lm_step singular JtJ", "lm_step indefinite JtJ", "least_squares", "assign_points", "scatter_rows",
    "stereo_match", "background_median", "update_background", "foreground_mask", "depth_points", "dbscan",
    "radius_components",
]  # fmt: skip
TRACKER_NAMES = ["BodyTracker.track", "GroupTracker.update_points", "GroupTracker.track", "PedestrianTracker.track",
                 "FaceTracker.start"]  # fmt: skip

def _kalman(rng):
    from gputrack.sim import problems

    return problems.kalman_mixed(rng, T=5, detections=3)


def op_cases(seed: int = 0) -> list[Case]:
    """Every public op with small valid arguments (seeded)."""
    from gputrack import ops
    from gputrack.models import upper_body
    from gputrack.sim import problems

    rng = np.random.default_rng(seed)
    cases = []
    chain = upper_body()
    P = chain.n_params
    params = (chain.rest_params()[None, :] + rng.normal(0, 0.2, (5, P))).astype(np.float32)
    cases.append(Case("forward_kinematics", lambda d, params: ops.forward_kinematics(d, chain, params),
                      {"params": params}, ("params",)))  # fmt: skip

    tf, rgb, dep, gray, depth, cam = problems.template_scene(rng, b=5, j=2, n=13, m=11, h=16, w=20)
    for name, fn in (("rgbd_cost", ops.rgbd_cost), ("rgbd_residuals", ops.rgbd_residuals)):
        cases.append(Case(
            name,
            # the scene is made in the call: its templates' and constants' mutations reach RgbdScene's checks
            lambda d, transforms, gray, depth_image, rgb, depth, lam, c_depth, depth_tol, fn=fn: fn(
                d, transforms, ops.RgbdScene(rgb, depth, cam, lam=lam, c_depth=c_depth, depth_tol=depth_tol), gray,
                depth_image),
            {"transforms": tf, "gray": gray, "depth_image": depth, "rgb": rgb, "depth": dep, "lam": 0.9,
             "c_depth": 0.05, "depth_tol": 0.0},
            ("transforms", "gray", "depth_image"),
            {"lam": [1.1, -0.1], "c_depth": [-1.0], "depth_tol": [-1.0], "rgb": [("a", "b"), dep], "depth": [rgb]},
            nan_ok=("depth_image",),  # 0 or non-finite: no measurement
        ))  # fmt: skip

    img = rng.uniform(0, 1, (18, 21)).astype(np.float32)
    tpl = rng.uniform(0, 1, (3, 4, 4)).astype(np.float32)
    pts = rng.uniform(-1, 20, (4, 3, 2)).astype(np.float32)
    for name, fn in (("patch_ncc", ops.patch_ncc), ("patch_ncc_per_point", ops.patch_ncc_per_point)):
        cases.append(Case(name, lambda d, points2d, templates, image, fn=fn: fn(d, points2d, templates, image),
                          {"points2d": pts, "templates": tpl, "image": img}, ("points2d", "templates", "image")))

    cand = (chain.rest_params()[None, :] + rng.normal(0, 0.1, (3, P))).astype(np.float32)
    sigma = np.full(P, 0.05, np.float32)
    cases.append(Case(
        "sample_around",
        lambda d, candidates, sigma, n, seed, keep_candidates: ops.sample_around(
            d, candidates, sigma, n, seed, keep_candidates=keep_candidates),
        {"candidates": cand, "sigma": sigma, "n": 9, "seed": 7, "keep_candidates": True},
        ("candidates", "sigma"), {"n": [2, 10**12], "seed": [2**64, -5]},
    ))  # fmt: skip
    scores = rng.normal(size=37).astype(np.float32)
    rows = rng.normal(size=(37, 4)).astype(np.float32)
    cases.append(Case("best_k", lambda d, scores, k, rows: ops.best_k(d, scores, k, rows),
                      {"scores": scores, "k": 5, "rows": rows}, ("scores", "rows"), {"k": [38, 2**40]},
                      nan_ok=("scores", "rows")))  # NaN scores rank last; rows are copied, not computed with

    body = _body_scene()
    if body is not None:
        bchain, frame, brgb, bdep, bcam, bcand, bsigma = body
        bscene = ops.RgbdScene(brgb, bdep, bcam)
        cases.append(Case(
            "pf_stage",
            lambda d, candidates, sigma, gray, depth_image, n, seed, k, scene: ops.pf_stage(
                d, bchain, candidates, sigma, n, seed, scene, gray, depth_image, k=k),
            {"candidates": bcand, "sigma": bsigma, "gray": frame.gray, "depth_image": frame.depth, "n": 40, "seed": 3,
             "k": 4, "scene": bscene},
            ("candidates", "sigma", "gray", "depth_image"), {"n": [3, 2**40], "k": [41], "scene": [brgb]}, scale=50.0,
            nan_ok=("depth_image",),
        ))  # fmt: skip
        bparams = (bcand[:3] + 0.001).astype(np.float32)
        cases.append(Case(
            "pose_residuals",
            lambda d, params, gray, depth_image, scene: ops.pose_residuals(d, bchain, params, scene, gray, depth_image),
            {"params": bparams, "gray": frame.gray, "depth_image": frame.depth, "scene": bscene},
            ("params", "gray", "depth_image"), {"scene": [brgb]}, nan_ok=("depth_image",),
        ))  # fmt: skip

    k = _kalman(rng)
    cases.append(Case("kf_predict", lambda d, x, P, F, Q: ops.kf_predict(d, x, P, F, Q),
                      {"x": k["x"], "P": k["P"], "F": k["F"], "Q": k["Q"]}, ("x", "P", "F", "Q"), scale=100.0))
    cases.append(Case(
        "kf_update", lambda d, x, P, z, H, R, mask, gain_scale: ops.kf_update(d, x, P, z, H, R, mask=mask,
                                                                              gain_scale=gain_scale),
        {"x": k["x"], "P": k["P"], "z": k["z"], "H": k["H"], "R": k["R"], "mask": k["mask"], "gain_scale": k["gain"]},
        ("x", "P", "z", "H", "R", "mask", "gain_scale"), scale=100.0, nan_ok=("z",),  # NaN in z: missing
    ))  # fmt: skip
    cases.append(Case(
        "ekf_update_stereo", lambda d, x, P, z, R, f, b: ops.ekf_update_stereo(d, x, P, z, R, f=f, b=b),
        {"x": k["x"], "P": k["P"], "z": k["zs"] + 0.5, "R": k["R"], "f": k["f"], "b": k["b"]},
        ("x", "P", "z", "R"), {"f": [0.0, -1.0], "b": [0.0]}, scale=100.0, nan_ok=("z",),
    ))  # fmt: skip
    cases.append(Case("mahalanobis", lambda d, x, P, H, R, z: ops.mahalanobis(d, x, P, H, R, z),
                      {"x": k["x"], "P": k["P"], "H": k["H"], "R": k["R"], "z": k["det"]}, ("x", "P", "H", "R", "z"),
                      scale=100.0))  # fmt: skip
    singular = k["P"].copy()
    singular[0] = 0.0  # a singular covariance (S = R stays definite)
    indefinite = k["P"].copy()
    indefinite[1] = -np.eye(6, dtype=np.float32)
    for label, PP in (("singular P", singular), ("indefinite P", indefinite)):
        cases.append(Case(f"kf_update {label}", lambda d, P: ops.kf_update(d, k["x"], P, k["z"], k["H"], k["R"]),
                          {"P": PP}, ("P",), scale=100.0))

    def gate(d, x, P, z, threshold, max_pairs):
        g = ops.gate_pairs(d, x, P, k["H"], k["R"], z, threshold, max_pairs=max_pairs)
        return g

    def gate_post(g):
        count, det, d2, trace = (gputrack.to_numpy(a) for a in g)
        keep = np.arange(det.shape[1])[None, :] < np.minimum(count, det.shape[1])[:, None]
        return [count, np.where(keep, det, -1), np.where(keep, d2, 0), trace]

    cases.append(Case("gate_pairs", gate, {"x": k["x"], "P": k["P"], "z": k["det"], "threshold": 50.0, "max_pairs": 2},
                      ("x", "P", "z"), {"max_pairs": [0, 2**40]}, post=gate_post, scale=100.0))  # fmt: skip

    J, r, C = problems.lm_batch(rng, B=3, M=9, P=4, dtype=np.float32)
    cases.append(Case("normal_equations", lambda d, J, r: ops.normal_equations(d, J, r), {"J": J, "r": r}, ("J", "r"),
                      scale=100.0))  # fmt: skip
    JtJ = np.einsum("bmp,bmq->bpq", J, J).astype(np.float32)
    Jtr = np.einsum("bmp,bm->bp", J, r).astype(np.float32)
    cases.append(Case("lm_step", lambda d, JtJ, Jtr, damping: ops.lm_step(d, JtJ, Jtr, damping),
                      {"JtJ": JtJ, "Jtr": Jtr, "damping": C}, ("JtJ", "Jtr", "damping"), scale=1000.0))
    cases.append(Case("lm_solve", lambda d, J, r, damping: ops.lm_solve(d, J, r, damping),
                      {"J": J, "r": r, "damping": C}, ("J", "r", "damping"), scale=1000.0))
    sing = JtJ.copy()
    sing[0] = 0.0
    indef = JtJ.copy()
    indef[1] = -np.eye(4, dtype=np.float32) * 5
    for label, A in (("singular JtJ", sing), ("indefinite JtJ", indef)):
        cases.append(Case(f"lm_step {label}", lambda d, JtJ: ops.lm_step(d, JtJ, Jtr, np.zeros(3, np.float32)),
                          {"JtJ": A}, ("JtJ",), scale=1000.0))

    res, x0 = problems.exponential_fit()

    def lsq(d, x0, max_iter):
        out = ops.least_squares(res, x0, device=d, max_iter=max_iter, dtype=np.float32)
        return out.x, out.status

    cases.append(Case("least_squares", lsq, {"x0": x0.astype(np.float32), "max_iter": 8}, ("x0",),
                      {"max_iter": [0, -1]}, scale=1e3))  # fmt: skip

    T, N = 3, 40
    means = np.zeros((T, 6), np.float32)
    means[:, [0, 2, 4]] = rng.uniform(-1000, 1000, (T, 3)) + [0, 0, 5000]
    S = np.tile(np.diag([2e5, 16, 2e5, 16, 2e5, 16]).astype(np.float32), (T, 1, 1))
    owner = rng.integers(0, T, N)
    y = (means[owner][:, [0, 2, 4]] + rng.normal(0, 300, (N, 3))).astype(np.float32)
    lam = rng.normal(0, 3, (N, 3)).astype(np.float32)
    cases.append(Case(
        "assign_points", lambda d, points, velocities, means, spreads, gamma: ops.assign_points(
            d, points, velocities, means, spreads, gamma),
        {"points": y, "velocities": lam, "means": means, "spreads": S, "gamma": 11.34},
        ("points", "velocities", "means", "spreads"), {"gamma": [-1.0]}, scale=100.0,
        nan_ok=("points", "velocities"),  # a NaN row: no point
    ))  # fmt: skip

    dst = rng.normal(size=(9, 4)).astype(np.float32)

    def scatter(d, index, src):  # a fresh destination on the device each call (written in place)
        return ops.scatter_rows(d, np.array(dst) if d.backend == "numpy" else d.asarray(dst), index, src)

    cases.append(Case("scatter_rows", scatter,
                      {"index": np.array([4, 0, 7], np.int32), "src": rng.normal(size=(3, 4)).astype(np.float32)},
                      ("index", "src")))  # fmt: skip

    base = rng.integers(0, 256, (20, 44)).astype(np.uint8)
    left, right = base[:, :38], base[:, 4:42]
    cases.append(Case("stereo_match", lambda d, left, right, max_disparity, block: ops.stereo_match(
        d, left, right, max_disparity=max_disparity, block=block),
        {"left": left, "right": right, "max_disparity": 8, "block": 5}, ("left", "right"),
        {"block": [4, 33], "max_disparity": [2**40]}))  # fmt: skip

    frames = rng.integers(0, 4000, (5, 9, 13)).astype(np.uint16)
    bg = frames.mean(axis=0).astype(np.float32)
    cases.append(Case("background_median", lambda d, frames: ops.background_median(d, frames, missing=0),
                      {"frames": frames}, ("frames",)))
    cases.append(Case("update_background", lambda d, background, frame, rate: ops.update_background(
        d, background, frame, rate=rate, missing=0), {"background": bg, "frame": frames[1], "rate": 0.1},
        ("background", "frame"), {"rate": [1.5, -0.1]}, nan_ok=("background",)))  # fmt: skip
    cases.append(Case("foreground_mask", lambda d, frame, background, threshold: ops.foreground_mask(
        d, frame, background, threshold, missing=0), {"frame": frames[0], "background": bg, "threshold": 100.0},
        ("frame", "background"), {"threshold": [-1.0]}, nan_ok=("background",)))  # fmt: skip
    from gputrack.models.camera import Camera

    dcam = Camera(10.0, 10.0, 6.0, 4.0)

    def dpoints(d, depth, background, n_points, seed):
        p, n = ops.depth_points(d, depth, background, dcam, n_points=n_points, seed=seed)
        return p, n

    cases.append(Case("depth_points", dpoints, {"depth": frames[0], "background": bg, "n_points": 16, "seed": 5},
                      ("depth", "background"), {"n_points": [2**40], "seed": [2**32]},
                      nan_ok=("background",)))  # fmt: skip
    pts2 = np.concatenate([rng.normal(0, 0.1, (15, 2)), rng.normal(1, 0.1, (15, 2))]).astype(np.float32)
    cases.append(Case("dbscan", lambda d, points, eps, min_samples: ops.dbscan(d, points, eps, min_samples),
                      {"points": pts2, "eps": 0.1, "min_samples": 3}, ("points",), {"eps": [-1.0], "min_samples": [0]},
                      nan_ok=("points",)))  # fmt: skip
    cases.append(Case("radius_components", lambda d, points, radius: ops.radius_components(d, points, radius),
                      {"points": pts2, "radius": 0.1}, ("points",), {"radius": [-1.0]}, nan_ok=("points",)))
    return cases


_BODY: dict = {}


def _body_scene():
    """A 640 x 480 frame of the body simulator, the tracker's templates, candidates and sigma
    (built once per process with the reference device)."""
    if "scene" not in _BODY:
        from gputrack.sim import sequence
        from gputrack.trackers.body import BodyTracker, BodyTrackerConfig
        from gputrack.models.upper_body import pf_sigma

        seq = sequence("arm_cross", frames=2, seed=0)
        frame = seq[1]  # rendered once (indexing a sequence renders the frame)
        tracker = BodyTracker(REF, seq.params[0], config=BodyTrackerConfig(lm_iterations=0, samples=40))
        tracker.track(frame.gray, frame.depth)
        rgb, dep = tracker._templates
        rng = np.random.default_rng(3)
        cand = (seq.params[1][None] + rng.normal(0, 0.01, (4, seq.chain.n_params))).astype(np.float32)
        sigma = (pf_sigma(seq.chain) * tracker._groups()[0]).astype(np.float32)
        _BODY["scene"] = (seq.chain, frame, rgb, dep, tracker.camera, cand, sigma)
        _BODY["seq"] = seq
    return _BODY["scene"]


def body_sequence():
    _body_scene()
    return _BODY["seq"]


def huge_count(clean, value) -> bool:
    """Whether ``value`` given to an argument whose valid value is ``clean`` is a huge count, size or
    seed (run in the limited child process, tests/fuzz_child.py)."""
    is_int = lambda v: isinstance(v, (int, np.integer)) and not isinstance(v, bool)  # noqa: E731
    return is_int(clean) and is_int(value) and abs(int(value)) >= 2**31


#: failures with a known cause in an op this suite's authors do not own: (case, mutation) -> the
#: cause. test_fuzz.py marks the test xfail naming them; a new failure still fails it.
KNOWN_DEFECTS: dict = {}


#: (case, mutation prefix) -> cause: the mutations of arrays on a device (the device's own, another's)
KNOWN_PREFIXES: dict = {}


def known_defect(case: str, what: str) -> str | None:
    found = KNOWN_DEFECTS.get((case, what))
    if found is None:
        found = next((why for (c, prefix), why in KNOWN_PREFIXES.items() if c == case and what.startswith(prefix)), None)
    return found


# -- tracker entry points ---------------------------------------------------------------------------------
def _per_device(make):
    """``make(device)`` once per device (a tracker keeps its state and its compiled stages)."""
    made: dict = {}

    def get(device):
        key = id(device)
        if key not in made or made[key][0] is not device:
            made[key] = (device, make(device))
        return made[key][1]

    return get


def tracker_cases(face: bool = True) -> list[Case]:
    """The trackers' per-frame entry points with a small valid frame (``face``: with FaceTracker.start,
    which loads the ICT face model). A refused frame must leave the tracker usable: the clean call
    runs after the mutations again (test_fuzz.py)."""
    import warnings

    from gputrack.models import Camera, StereoCamera
    from gputrack.trackers.body import BodyTracker, BodyTrackerConfig
    from gputrack.trackers.groups import GroupTracker
    from gputrack.trackers.pedestrians import PedestrianConfig, PedestrianTracker

    cases = []
    seq = body_sequence()
    frame = _body_scene()[1]
    body = _per_device(lambda d: BodyTracker(d, seq.params[0], config=BodyTrackerConfig(
        lm_iterations=1, samples=40, stages=1)))  # fmt: skip
    cases.append(Case("BodyTracker.track", lambda d, gray, depth: body(d).track(gray, depth),
                      {"gray": frame.gray, "depth": frame.depth}, ("gray", "depth"), tracker=True, nan_ok=("depth",)))

    cam = StereoCamera(f=513.5, cx=320.0, cy=240.0, b=120.0)
    rng = np.random.default_rng(5)
    xyz = (rng.normal(0, 200, (30, 3)) + [0, 0, 5000]).astype(np.float32)
    vel = rng.normal(0, 5, (30, 3)).astype(np.float32)
    groups = _per_device(lambda d: GroupTracker(d, camera=cam))
    cases.append(Case("GroupTracker.update_points", lambda d, xyz, velocity: groups(d).update_points(xyz, velocity),
                      {"xyz": xyz, "velocity": vel}, ("xyz", "velocity"), tracker=True,
                      nan_ok=("xyz", "velocity")))  # fmt: skip
    left = rng.integers(0, 256, (48, 64)).astype(np.uint8)
    right = np.roll(left, -3, axis=1)
    cases.append(Case("GroupTracker.track", lambda d, left, right: groups(d).track(left, right),
                      {"left": left, "right": right}, ("left", "right"), tracker=True))  # fmt: skip

    small = Camera(160 / (2 * np.tan(np.radians(29.5))), 120 / (2 * np.tan(np.radians(23.0))), 79.5, 59.5)
    from gputrack.benchmarks.pedestrians import crowd_depth

    bg = crowd_depth(small, (120, 160), np.zeros((0, 2)))
    frame = crowd_depth(small, (120, 160), np.array([[0.0, 3000.0]]))

    def pedestrians(d):
        trk = PedestrianTracker(d, camera=small, config=PedestrianConfig())
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # few background frames
            trk.learn_background(np.stack([bg] * 3))
        return trk

    peds = _per_device(pedestrians)
    cases.append(Case("PedestrianTracker.track", lambda d, depth: peds(d).track(depth), {"depth": frame}, ("depth",),
                      tracker=True))  # fmt: skip

    face = _face_tracker() if face else None
    if face is not None:
        make, frames, landmarks = face
        faces = _per_device(make)
        cases.append(Case("FaceTracker.start", lambda d, frames, landmarks: faces(d).start(frames, landmarks)
                          and None, {"frames": frames, "landmarks": landmarks}, ("frames", "landmarks"),
                          tracker=True))  # fmt: skip
    return cases


def _face_tracker():
    """(make(device), the first 7 frames, their feature points) of a short simulated face sequence,
    or None without the ICT face data."""
    try:
        from gputrack.models.face import FaceModel, load_ict
        from gputrack.sim.face import face_sequence
        from gputrack.trackers.face import FaceConfig, FaceTracker

        ict = load_ict()
    except (FileNotFoundError, OSError):
        return None
    if "face" not in _BODY:
        model = FaceModel.from_ict(ict)
        seq = face_sequence("turns", frames=7, ict=ict)
        frames = [seq[k] for k in range(7)]
        gray = np.array([f.gray for f in frames])
        lm = np.array([f.landmarks2d for f in frames])
        _BODY["face"] = (lambda d: FaceTracker(d, model, seq.camera, FaceConfig(particles=16)), gray, lm)
    return _BODY["face"]
