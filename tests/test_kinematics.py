import numpy as np
import pytest
from tolerances import assert_matches

import gputrack
from gputrack.abi import ANGLE_MAX
from gputrack.backends.reference.kinematics import forward_kinematics as reference
from gputrack.models import Chain, Part, Shape, rigid, upper_body
from gputrack.ops.kinematics import forward_kinematics

DEG = np.pi / 180


def random_params(chain, b, seed, spread=1.0):
    """Poses around the rest pose: angles +-spread rad, torso +-200 mm, shoulders +-30 mm."""
    rng = np.random.default_rng(seed)
    scale = np.ones(chain.n_params)
    scale[3:6] = 200.0
    scale[14:] = 30.0
    return chain.rest_params() + rng.uniform(-spread, spread, (b, chain.n_params)) * scale


def dtypes(device):
    return (np.float32, np.float64) if device.fp64 else (np.float32,)


# -- hand-written eq. 6-11 -------------------------------------------------------------------------
def h(r, t):
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def rx(a):  # eq. 7
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a):  # eq. 8
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(a):  # eq. 9
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def by_hand(p, t_rs, t_ls, t_e):
    d = h(rz(p[0]) @ ry(p[1]) @ rx(p[2]), p[3:6])  # eq. 6
    d_ru = h(rz(p[6]) @ ry(p[7]), t_rs)  # eq. 10
    d_lu = h(rz(p[8]) @ ry(p[9]), t_ls)
    d_rl = h(rz(p[10]) @ ry(p[11]), t_e)  # eq. 11
    d_ll = h(rz(p[12]) @ ry(p[13]), t_e)
    mats = [d, d @ d_ru, d @ d_lu, d @ d_ru @ d_rl, d @ d_lu @ d_ll]  # eq. 2-4
    return np.stack([m[:3] for m in mats])


def test_reference_matches_equations_6_to_11():
    chain = upper_body()
    t_rs, t_ls = chain.parts[1].offset, chain.parts[2].offset
    t_e = chain.parts[3].offset
    assert chain.parts[4].offset == t_e and t_e[1:] == (0.0, 0.0) and t_e[0] > 0
    for p in random_params(chain, 5, seed=3):
        got = reference(None, chain, p[None])[0]
        np.testing.assert_allclose(got, by_hand(p, t_rs, t_ls, t_e), rtol=1e-12, atol=1e-9)


def test_reference_known_pose():
    """Arms straight down (th = 90 deg), torso at (0, 0, 2000): positions checkable by eye."""
    chain = upper_body()
    p = np.zeros(14)
    p[5] = 2000.0
    p[6] = p[8] = 90 * DEG
    t = reference(None, chain, p[None])[0]
    sx, sy, sz = chain.parts[2].offset
    lu = chain.parts[4].offset[0]
    np.testing.assert_allclose(t[2, :, 3], [sx, sy, 2000 + sz], atol=1e-9)  # left shoulder
    np.testing.assert_allclose(t[2, :, 0], [0, 1, 0], atol=1e-12)  # upper arm axis points down (+y)
    np.testing.assert_allclose(t[4, :, 3], [sx, sy + lu, 2000 + sz], atol=1e-9)  # left elbow
    np.testing.assert_allclose(t[3, :, 3], [-sx, sy + lu, 2000 + sz], atol=1e-9)  # right elbow (mirrored)
    # torso turned 90 deg about its vertical axis (ph): torso x now points along camera -z
    p[1] = 90 * DEG
    t = reference(None, chain, p[None])[0]
    np.testing.assert_allclose(t[0, :, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(t[2, :, 3], [sz, sy, 2000 - sx], atol=1e-9)
    # elbow bent forward 90 deg (ph_LE): the forearm points towards the camera (-z)
    p[1] = 0.0
    p[13] = 90 * DEG
    t = reference(None, chain, p[None])[0]
    np.testing.assert_allclose(t[4, :, 0], [0, 0, -1], atol=1e-12)


@pytest.mark.parametrize("shoulders", [False, True])
@pytest.mark.parametrize("b", [1, 13, 1500])
def test_matches_reference(device, b, shoulders):
    chain = upper_body(shoulders=shoulders)
    params = random_params(chain, b, seed=b)
    for dt in dtypes(device):
        p = params.astype(dt)
        got = forward_kinematics(device, chain, p)
        assert got.shape == (b, 5, 3, 4) and got.dtype == dt
        # translations are ~2000 mm: compare them relative to that scale
        want = reference(None, chain, p)
        got = gputrack.to_numpy(got)
        assert_matches(device, got[..., :3], want[..., :3], dt)
        assert_matches(device, got[..., 3] / 2000.0, want[..., 3] / 2000.0, dt)


def test_large_angles(device):
    """Angles far outside [-pi, pi] (every quadrant of the sin/cos range reduction)."""
    chain = upper_body()
    p = random_params(chain, 129, seed=4)
    p[:, [0, 1, 2, *range(6, 14)]] = np.random.default_rng(4).uniform(-20, 20, (129, 11))
    for dt in dtypes(device):
        got = gputrack.to_numpy(forward_kinematics(device, chain, p.astype(dt)))
        want = reference(None, chain, p.astype(dt))
        assert_matches(device, got / 2000.0, want / 2000.0, dt)


def test_angles_past_the_limit_are_clamped_on_every_backend(device):
    """Finite angles beyond ANGLE_MAX = 2**15 rad are clamped to it everywhere (Taichi gave NaN from
    1e20 rad, and its float32 sine was 1e-3 off at 3e4 rad: fast math undid the argument reduction);
    angles up to the limit match the reference; inf and NaN angles still give non-finite transforms."""
    chain = upper_body()
    angles = [i for part in chain.parts for i in part.angles]
    values = np.array([1e2, 3e4, -ANGLE_MAX, ANGLE_MAX, 5e4, 1e20, -3e38, 3e38])
    p = np.repeat(random_params(chain, 1, seed=9), len(values), axis=0)
    p[:, angles] = values[:, None] * np.linspace(1.0, 0.5, len(angles))  # every angle its own value
    for dt in dtypes(device):
        got = gputrack.to_numpy(forward_kinematics(device, chain, p.astype(dt)))
        want = reference(None, chain, p.astype(dt))
        assert np.isfinite(got).all()
        assert_matches(device, got[..., :3], want[..., :3], dt)
        assert_matches(device, got[..., 3] / 2000.0, want[..., 3] / 2000.0, dt)
    clamped = p.copy()
    clamped[:, angles] = np.clip(p[:, angles], -ANGLE_MAX, ANGLE_MAX)
    np.testing.assert_array_equal(reference(None, chain, p), reference(None, chain, clamped))
    if device.backend != "numpy":  # host params are checked; device params carry inf / NaN through
        host = np.repeat(p[:1], 2, axis=0).astype(np.float32)
        host[0, angles[0]], host[1, angles[0]] = np.inf, np.nan
        got = gputrack.to_numpy(forward_kinematics(device, chain, device.asarray(host)))
        assert not np.isfinite(got[0, 0]).all() and not np.isfinite(got[1, 0]).all()


def test_device_arrays_in_and_rotations_orthonormal(device):
    chain = upper_body()
    p = device.asarray(random_params(chain, 129, seed=7).astype(np.float32))
    got = gputrack.to_numpy(forward_kinematics(device, chain, p))
    r = got[..., :3]
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), eye, atol=2e-6)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=2e-6)


def test_shoulder_parameters_equal_fixed_offsets(device):
    """The 20-parameter chain with t_RS, t_LS set to the generic positions is the 14-parameter chain."""
    c14, c20 = upper_body(), upper_body(shoulders=True)
    p14 = random_params(c14, 13, seed=1)
    p20 = np.concatenate([p14, np.tile(c20.rest_params()[14:], (13, 1))], axis=1)
    a = gputrack.to_numpy(forward_kinematics(device, c14, p14.astype(np.float32)))
    b = gputrack.to_numpy(forward_kinematics(device, c20, p20.astype(np.float32)))
    assert_matches(device, b, a, scale=100)
    # moving the right shoulder by (10, -20, 5) in torso coordinates moves the right arm only
    p20[:, 14:17] += [10.0, -20.0, 5.0]
    b = gputrack.to_numpy(forward_kinematics(device, c20, p20.astype(np.float32)))
    shift = np.einsum("bij,j->bi", a[:, 0, :, :3], [10.0, -20.0, 5.0])
    np.testing.assert_allclose(b[:, 1, :, 3] - a[:, 1, :, 3], shift, atol=2e-3)
    np.testing.assert_allclose(b[:, 3, :, 3] - a[:, 3, :, 3], shift, atol=2e-3)
    np.testing.assert_allclose(b[:, [0, 2, 4]], a[:, [0, 2, 4]], atol=2e-3)


def test_generic_chains(device):
    """Not hard-coded to the upper body: a 7-part chain with every joint kind, and a rigid part."""
    cap = Shape("capsule", 0, 0.0, 100.0, (20.0, 20.0))
    parts = (
        Part("base", -1, "zyx", (0, 1, 2), translation=(3, 4, 5), shape=cap),
        Part("a", 0, "x", (6,), offset=(10.0, 0.0, 0.0), shape=cap),
        Part("b", 1, "xyz", (7, 8, 9), offset=(100.0, 5.0, -3.0), shape=cap),
        Part("c", 0, "", (), offset=(0.0, 50.0, 0.0), translation=(-1, 10, -1), shape=cap),
        Part("d", 2, "yz", (11, 12), offset=(100.0, 0.0, 0.0), translation=(13, -1, 14), shape=cap),
        Part("e", 3, "zz", (6, 12), offset=(1.0, 2.0, 3.0), shape=cap),
        Part("f", 5, "y", (0,), shape=cap),
    )
    chain = Chain(parts, 15, tuple(f"p{i}" for i in range(15)), (0.0,) * 5 + (500.0,) + (0.0,) * 9)
    rng = np.random.default_rng(11)
    params = rng.uniform(-2, 2, (13, 15)) * np.r_[[1] * 3, [100] * 3, [1] * 4, [30], [1] * 2, [30] * 2]
    for dt in dtypes(device):
        got = gputrack.to_numpy(forward_kinematics(device, chain, params.astype(dt)))
        want = reference(None, chain, params.astype(dt))
        assert got.shape == (13, 7, 3, 4)
        assert_matches(device, got / 1000.0, want / 1000.0, dt)
    one = rigid()
    p = rng.normal(0, 1, (1, 6))
    got = gputrack.to_numpy(forward_kinematics(device, one, p.astype(np.float32)))
    want = np.concatenate([rz(p[0, 0]) @ ry(p[0, 1]) @ rx(p[0, 2]), p[0, 3:, None]], axis=1)
    np.testing.assert_allclose(got[0, 0], want, atol=2e-6)


FUSED_CL = """
#include "gt_kinematics.clh"
__kernel void fused(__global const float *params, __global const int *table, __global const float *offsets,
                    __global float *scratch, __global float *tips, const int P, const int J)
{
    const int b = get_global_id(0);
    __global float *o = scratch + (size_t)b * J * 12;
    gt_fk_pose(params + (size_t)b * P, table, offsets, o, J);
    /* the camera position of each part's point (100, 0, 0): a fused stage after the kinematics */
    for (int j = 0; j < J; ++j)
        for (int r = 0; r < 3; ++r)
            tips[(b * J + j) * 3 + r] = 100.0f * o[j * 12 + 4 * r] + o[j * 12 + 4 * r + 3];
}
"""


def test_building_blocks_for_fused_kernels(device):
    """gt_kinematics.clh (OpenCL, chain tables) and pose_f32 (Taichi, the chain's structure as a
    compile-time value) give the op's transforms inside another kernel."""
    if device.backend == "numpy":
        pytest.skip("the reference has no kernels")
    from gputrack.models.chain import chain_tables

    chain = upper_body()
    p = random_params(chain, 13, seed=9).astype(np.float32)
    dp = device.asarray(p)
    table, offsets = chain_tables(device, chain)
    scratch = device.empty((13, 5, 3, 4), np.float32)
    tips = device.empty((13, 5, 3), np.float32)
    if device.backend == "opencl":
        import pyopencl as cl

        from gputrack.backends.opencl.program import build_options

        prg = cl.Program(device.context, FUSED_CL).build(options=build_options())  # the ABI defines too
        prg.fused(device.queue, (13,), None, dp.buffer.data, table.buffer.data, offsets.buffer.data,
                  scratch.buffer.data, tips.buffer.data, np.int32(14), np.int32(5))  # fmt: skip
    else:
        from gputrack.backends.taichi.kinematics import pose_f32
        from gputrack.backends.taichi.runtime import ti

        @ti.kernel
        def fused(
            params: ti.types.ndarray(dtype=ti.f32, ndim=2),
            offsets: ti.types.ndarray(dtype=ti.f32, ndim=2),
            scratch: ti.types.ndarray(dtype=ti.f32, ndim=4),
            tips: ti.types.ndarray(dtype=ti.f32, ndim=3),
            structure: ti.template(),
        ):
            for b in range(params.shape[0]):
                pose_f32(params, b, structure, offsets, scratch)
                for j in range(scratch.shape[1]):
                    for r in ti.static(range(3)):
                        tips[b, j, r] = 100.0 * scratch[b, j, r, 0] + scratch[b, j, r, 3]

        fused(dp.buffer, offsets.buffer, scratch.buffer, tips.buffer, chain.structure())
    want = reference(None, chain, p.astype(np.float64))
    assert_matches(device, scratch.numpy()[..., :3], want[..., :3])
    assert_matches(device, tips.numpy() / 2000.0, (100.0 * want[..., 0] + want[..., 3]) / 2000.0)


def test_chain_tables_uploaded_once(device):
    chain = upper_body()
    p = device.asarray(random_params(chain, 13, seed=2).astype(np.float32))
    forward_kinematics(device, chain, p)
    before = device.transfers.copy()
    for _ in range(3):
        out = forward_kinematics(device, chain, p)
    device.synchronize()
    moved = device.transfers - before
    assert (moved.h2d, moved.d2h) == (0, 0)
    assert out.shape == (13, 5, 3, 4)


def test_out_argument(device):
    chain = upper_body()
    p = random_params(chain, 13, seed=5).astype(np.float32)
    out = device.empty((13, 5, 3, 4), np.float32)
    got = forward_kinematics(device, chain, p, out=out)
    assert got is out
    want = reference(None, chain, p)
    assert_matches(device, gputrack.to_numpy(out)[..., :3], want[..., :3])
    with pytest.raises(ValueError, match=r"out: expected a float32 array of shape \(13, 5, 3, 4\), got float32 \(12,"):
        forward_kinematics(device, chain, p, out=device.empty((12, 5, 3, 4), np.float32))
    with pytest.raises(ValueError, match=r"out: expected a float32 array of shape \(13, 5, 3, 4\), got int32 \(13, 5"):
        forward_kinematics(device, chain, p, out=device.empty((13, 5, 3, 4), np.int32))
    if device.backend != "numpy":
        with pytest.raises(TypeError, match=f"out: expected a writable array on {device.spec}"):
            forward_kinematics(device, chain, p, out=np.empty((13, 5, 3, 4), np.float32))


def test_bad_input(device):
    chain = upper_body()
    good = random_params(chain, 3, seed=0).astype(np.float32)
    with pytest.raises(ValueError, match=r"params: expected shape \(B=3, 14\), got \(3, 13\)"):
        forward_kinematics(device, chain, good[:, :13])
    with pytest.raises(ValueError, match="params: expected shape"):
        forward_kinematics(device, chain, good[0])
    with pytest.raises(ValueError, match=r"params: expected shape \(B=3, 20\)"):
        forward_kinematics(device, upper_body(shoulders=True), good)
    with pytest.raises(TypeError, match="params: expected dtype float32 or float64, got int32"):
        forward_kinematics(device, chain, good.astype(np.int32))
    bad = good.copy()
    bad[1, 4] = np.nan
    with pytest.raises(ValueError, match="params: expected finite values"):
        forward_kinematics(device, chain, bad)
    with pytest.raises(ValueError, match="at least one parameter vector"):
        forward_kinematics(device, chain, np.zeros((0, 14), np.float32))
    with pytest.raises(TypeError, match="chain: expected a gputrack.models.Chain"):
        forward_kinematics(device, "upper_body", good)
    with pytest.raises(TypeError, match="expected a gputrack.Device"):
        forward_kinematics("numpy", chain, good)
    if not device.fp64:
        with pytest.raises(TypeError, match="float64"):
            forward_kinematics(device, chain, good.astype(np.float64))


def test_chain_validation_and_sparsity():
    cap = Shape("capsule", 0, 0.0, 1.0, (1.0, 1.0))
    with pytest.raises(ValueError, match="parent: expected -1 or an earlier part"):
        Chain((Part("a", 1, "z", (0,), shape=cap), Part("b", -1, "z", (0,))), 1, ("p",), (0.0,))
    with pytest.raises(ValueError, match=r"parameter index 3 outside \[0, 2\)"):
        Chain((Part("a", -1, "zy", (0, 3)),), 2, ("p", "q"), (0.0, 0.0))
    with pytest.raises(ValueError, match="axes: expected up to 3"):
        Part("a", -1, "zw", (0, 1))
    with pytest.raises(ValueError, match="capsule radii"):
        Shape("capsule", 0, 0.0, 1.0, (1.0, 2.0))

    chain = upper_body()
    parts = np.repeat(np.arange(5), 3)
    mask = chain.jacobian_sparsity(parts)
    assert mask.shape == (15, 14) and mask.dtype == bool
    want = np.zeros((5, 14), bool)  # Fig. 2
    want[:, 0:6] = True
    want[1, 6:8] = want[2, 8:10] = True
    want[3, 6:8] = want[3, 10:12] = True
    want[4, 8:10] = want[4, 12:14] = True
    np.testing.assert_array_equal(mask, want[parts])
    mask20 = upper_body(shoulders=True).jacobian_sparsity(np.arange(5))
    np.testing.assert_array_equal(mask20[:, :14], want)
    np.testing.assert_array_equal(mask20[:, 14:17], np.array([[0, 1, 0, 1, 0]], bool).T.repeat(3, 1))
    np.testing.assert_array_equal(mask20[:, 17:20], np.array([[0, 0, 1, 0, 1]], bool).T.repeat(3, 1))
    with pytest.raises(ValueError, match=r"part indices in \[0, 5\)"):
        chain.jacobian_sparsity(np.array([0, 5]))
    with pytest.raises(ValueError, match="1-D integer array"):
        chain.jacobian_sparsity(np.zeros((2, 2)))


def test_selftest_passes(device):
    from gputrack.selftest import check_kinematics

    check_kinematics(device)
