"""gputrack.ops.model_template (paper 000 sec. 2.3 on the device): the render against the NumPy
reference (float32 against float64: equal up to a few silhouette pixels), the selection on the same
images exactly equal on every backend, the whole template close to the reference's, and the rule's
promises on the reference (strongest extrema first, spread fill, hidden parts, small pools)."""

import numpy as np
import pytest

import gputrack
from gputrack.models import upper_body
from gputrack.models.render import render
from gputrack.ops.model_template import (
    DeviceTemplate,
    model_images,
    model_template,
    render_model,
    select_template,
)

REF = gputrack.device("numpy")
CHAIN = upper_body()
DEG = np.pi / 180


def _poses():
    rest = CHAIN.rest_params()
    crossed = rest.copy()
    crossed[[6, 7, 9, 10]] = (-40 * DEG, 60 * DEG, 30 * DEG, -70 * DEG)  # arms across the torso
    side = rest.copy()
    side[1] = 90 * DEG  # side view: the right arm hangs behind the torso
    side[[11, 13]] = 0.0
    return {"rest": rest, "crossed": crossed, "side": side}


POSES = _poses()


def _render_f64(device) -> bool:
    """Whether ``device``'s backend renders in float64 (its ``render_dtype``): then its render is
    the reference's up to the float32 store."""
    return gputrack.ops.backend_module(device, "model_template").render_dtype(device) == np.float64


@pytest.mark.parametrize("pose", sorted(POSES))
def test_render_matches_reference(device, pose):
    want = render_model(REF, CHAIN, POSES[pose])
    wp, wv, wl = (np.array(a) for a in (want.part, want.values, want.local))
    got = render_model(device, CHAIN, POSES[pose])
    assert got.crop == want.crop
    r0, r1, c0, c1 = want.crop
    gp = device.to_numpy(got.part)[r0:r1, c0:c1]
    gv = device.to_numpy(got.values)[:, r0:r1, c0:c1]
    gl = device.to_numpy(got.local)[r0:r1, c0:c1]
    wp, wv, wl = wp[r0:r1, c0:c1], wv[:, r0:r1, c0:c1], wl[r0:r1, c0:c1]
    differ = gp != wp
    # rendered in float64: the reference's up to the float32 store (measured on PoCL and taichi:cpu:
    # 0 part pixels, depth and local bit-equal, gray 3.7e-9); else float32 (depth 2.6e-3 mm)
    f64 = _render_f64(device)
    most, zt, lt, gt = (2, 1e-3, 1e-4, 1e-6) if f64 else (0.002 * differ.size, 0.02, 0.02, 2e-4)
    assert differ.sum() <= most, f"{differ.sum()} of {differ.size} pixels differ in their part"
    both = ~differ & (wp >= 0)
    assert both.sum() > 5000
    np.testing.assert_allclose(gv[1][both], wv[1][both], rtol=0, atol=zt)  # depth Z, mm
    np.testing.assert_allclose(gl[both], wl[both], rtol=0, atol=lt)  # part-local point, mm
    np.testing.assert_allclose(gv[0][both], wv[0][both], rtol=0, atol=gt)  # gray


def _tracker_poses():
    import gputrack.sim

    seq = gputrack.sim.sequence("arm_cross", frames=12, seed=0).params[:12]
    return [*(POSES[k] for k in sorted(POSES)), *seq]


def test_tracker_templates_equal_reference(device):
    """Where the backend renders in float64 (its ``render_dtype``): the templates the tracker renders
    (the file's poses, the arm_cross sequence's) are the reference's exactly (a float32 render flips
    near-ties of the integers q and moves points by up to hundreds of mm)."""
    if not _render_f64(device):
        why = f"{device.spec} has no fp64" if not device.fp64 else f"the {device.backend} backend renders in float32 on {device.spec}"
        pytest.skip(f"{why}: a float32 render's templates are only close to the reference's")
    for i, p in enumerate(_tracker_poses()):
        want = model_template(REF, CHAIN, p)
        got = model_template(device, CHAIN, p)
        for kind, w, g in zip(("rgb", "depth"), want, got):
            np.testing.assert_array_equal(g.part, w.part, err_msg=f"pose {i}, {kind} template")
            np.testing.assert_array_equal(g.packed, w.packed, err_msg=f"pose {i}, {kind} template")


@pytest.mark.parametrize("pose", sorted(POSES))
@pytest.mark.parametrize("n, n_depth, window, border, spacing", [(128, 128, 5, 2, 4.0), (200, 60, 3, 1, 2.5),
                                                                  (64, 300, 7, 0, 6.0), (96, 96, 3, 3, 4.0)])  # fmt: skip
def test_selection_matches_reference_exactly(device, pose, n, n_depth, window, border, spacing):
    """The same images (the reference's rendering) give the same points on every backend."""
    _assert_selection_is_the_references(device, pose, n, n_depth, window, border, spacing)


def _assert_selection_is_the_references(device, pose, n, n_depth, window, border, spacing):
    """select_template on ``device`` of the reference's rendering of ``pose``: the reference's points."""
    r = render(CHAIN, POSES[pose], background=None, depth_step=0)
    values = np.stack([r.gray, r.depth])
    opts = {"window": window, "border": border, "spacing": spacing}
    want = select_template(REF, model_images(REF, r.part, values, r.local, 5), n, n_depth, **opts)
    got = select_template(device, model_images(device, r.part, values, r.local, 5), n, n_depth, **opts)
    for w, g in zip(want, got):
        assert isinstance(g, DeviceTemplate)
        np.testing.assert_array_equal(g.part, w.part, err_msg=f"{pose} n={n}")
        np.testing.assert_array_equal(g.packed, w.packed, err_msg=f"{pose} n={n}")


@pytest.mark.parametrize("pose", sorted(POSES))
def test_template_close_to_reference(device, pose):
    """Rendered and picked on the device: nearly every point is the reference's (a float32 render
    moves a few silhouette pixels and near-equal strengths)."""
    want = model_template(REF, CHAIN, POSES[pose])
    got = model_template(device, CHAIN, POSES[pose])
    for w, g in zip(want, got):
        np.testing.assert_array_equal(g.part, w.part)
        d = np.linalg.norm(g.xyz[:, None] - w.xyz[None], axis=2)
        same_part = g.part[:, None] == w.part[None]
        near = (np.where(same_part, d, np.inf).min(axis=1) < 0.5).mean()
        assert near > 0.9, f"{near:.2%} of the points are the reference's"


def test_bad_input():
    rest = CHAIN.rest_params()
    with pytest.raises(ValueError, match=r"params: expected shape \(14,\), got \(13,\)"):
        render_model(REF, CHAIN, rest[:13])
    with pytest.raises(ValueError, match="params: expected finite values"):
        render_model(REF, CHAIN, np.where(np.arange(14) == 3, np.nan, rest))
    with pytest.raises(ValueError, match="size: expected"):
        render_model(REF, CHAIN, rest, size=(1, 1))
    with pytest.raises(TypeError, match="chain: expected a gputrack.models.Chain"):
        render_model(REF, "body", rest)
    with pytest.raises(TypeError, match="camera: expected a gputrack.Camera"):
        render_model(REF, CHAIN, rest, camera=(525, 525, 320, 240))
    with pytest.raises(TypeError, match="texture: expected"):
        render_model(REF, CHAIN, rest, texture="wood")
    with pytest.raises(ValueError, match="shading: expected a number in"):
        render_model(REF, CHAIN, rest, shading=1.5)
    far = rest.copy()
    far[5] = -5000.0  # behind the camera
    with pytest.raises(ValueError, match="no visible model surface"):
        model_template(REF, CHAIN, far)
    images = render_model(REF, CHAIN, rest)
    for kw, match in (({"n": 0}, "n: expected an integer >= 1"), ({"window": 4}, "window: expected an odd size"),
                      ({"border": 9}, "border: expected 0 .. 8"), ({"spacing": 0.5}, "spacing: expected 1 .. 16"),
                      ({"n_depth": 2.5}, "n_depth: expected an integer")):  # fmt: skip
        with pytest.raises((ValueError, TypeError), match=match):
            select_template(REF, images, **kw)
    with pytest.raises(ValueError, match="n_parts: expected more than the largest part id 4, got 3"):
        model_images(REF, images.part, images.values, images.local, 3)
    with pytest.raises(ValueError, match="expected pixels of the model"):
        model_images(REF, np.full((4, 4), -1), np.zeros((2, 4, 4)), np.zeros((4, 4, 3)))


@pytest.mark.parametrize("wg", [1, 2, 32, 128])
def test_opencl_pick_per_work_group_matches_reference(device, wg, monkeypatch):
    """The OpenCL pick run by a work-group per part and kind (GPUs, ``gt_mt_emit_wg``; wg = 1: the
    CPU devices' ``gt_mt_emit``) gives the reference's points on the same images, on whatever
    device runs it: the heap, the compaction in pixel order, the centroid seed and the fill's ties."""
    if device.backend != "opencl":
        pytest.skip("OpenCL kernel variants")
    if wg > (device.info.max_work_group_size or wg):
        pytest.skip(f"{device.spec}: work-groups of at most {device.info.max_work_group_size}")
    from gputrack.backends.opencl import model_template as ocl

    monkeypatch.setattr(ocl, "emit_group", lambda dev: wg)
    for pose in sorted(POSES):
        for selection in ((128, 128, 5, 2, 4.0), (64, 300, 7, 0, 6.0), (1, 40, 5, 2, 16.0)):
            _assert_selection_is_the_references(device, pose, *selection)
