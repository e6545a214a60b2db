"""Paper 001's group simulator: rendered stereo geometry, ground truth and the observation generator
(host code: one run, no device)."""

import math

import cv2
import numpy as np
import pytest

from gputrack.sim.groups import BUMBLEBEE2, FPS, SCENES, SIZE, rig, scene

EMPTY = 4


def small(name, seed=0, **kw):
    kw = {"scale": 0.5, "supersample": 1, "empty_frames": EMPTY, **kw}
    return scene(name, np.random.default_rng(seed), **kw)


@pytest.fixture(scope="module")
def crossing():
    return small("crossing")


@pytest.fixture(scope="module")
def merging():
    return small("merging")


@pytest.fixture(scope="module")
def stairs():
    return small("stairs")


def test_rig_is_the_papers_bumblebee2():
    assert BUMBLEBEE2.f == pytest.approx(513.5, abs=0.1) and BUMBLEBEE2.b == 120.0 and SIZE == (640, 480)
    assert FPS == 48.0
    r = rig()
    assert r.mount_mm == 5100.0 and r.tilt_deg == 40.0 and r.size == (640, 480)
    # the optical axis meets the floor at 5.1 m / tan 40 deg; the world origin is below the camera
    hit = r.to_camera([0.0, 5100.0 / math.tan(math.radians(40.0)), 0.0])
    assert hit[:2] == pytest.approx([0.0, 0.0], abs=1e-6)
    assert hit[2] == pytest.approx(5100.0 / math.sin(math.radians(40.0)))
    assert r.to_camera([0.0, 0.0, 0.0])[1] > 0  # the floor is below (camera y down)
    p = np.array([[300.0, 7000.0, 1200.0]])
    assert r.to_world(r.to_camera(p)) == pytest.approx(p)
    assert r.centre("right") - r.centre("left") == pytest.approx([120.0, 0.0, 0.0])
    st = small("stairs", frames=EMPTY + 2).rig
    assert st.mount_mm == 2100.0 and st.tilt_deg == 15.0


def test_frame_shapes_empty_frames_and_background(crossing):
    f0, f1 = crossing[0], crossing[EMPTY]
    for f in (f0, f1):
        for img in (f.left, f.right, f.background_left, f.background_right):
            assert img.dtype == np.uint8 and img.shape == (240, 320)
        assert f.person_id.dtype == np.int32 and f.depth.shape == (240, 320)
    assert (f0.person_id == -1).all() and not f0.truth.present.any() and len(f0.truth.group_ids) == 0
    assert f1.truth.present.all() and set(np.unique(f1.person_id)) == {-1, 0, 1, 2, 3, 4}
    # the background pair is the frame without its people, with the frame's exposure (noise sigma 2)
    bg = f1.person_id == -1
    diff = f1.left.astype(float) - f1.background_left
    assert abs(diff[bg].mean()) < 0.2 and 1.5 < diff[bg].std() < 2.5
    assert np.abs(diff[~bg]).mean() > 10.0
    assert f1.left.std() > 20.0  # textured


def test_exposure_changes_per_frame_and_noise_free_background_matches():
    sc = small("merging", noise=0.0, exposure=0.05, frames=EMPTY + 3)
    a, b = sc[EMPTY], sc[EMPTY + 1]
    assert a.gain != b.gain
    assert np.array_equal(a.left[a.person_id == -1], a.background_left[a.person_id == -1])
    ra = (a.background_left.astype(float) - a.offset) / a.gain
    rb = (b.background_left.astype(float) - b.offset) / b.gain
    inside = (a.background_left > 5) & (a.background_left < 250) & (b.background_left > 5) & (b.background_left < 250)
    assert np.abs(ra - rb)[inside].max() <= 0.5 / a.gain + 0.5 / b.gain + 1e-6  # uint8 rounding


def test_determinism_for_a_seed():
    a, b, c = small("crossing", frames=EMPTY + 3), small("crossing", frames=EMPTY + 3), small("crossing", 1, frames=EMPTY + 3)
    fa, fb, fc = a[EMPTY + 2], b[EMPTY + 2], c[EMPTY + 2]
    assert np.array_equal(fa.left, fb.left) and np.array_equal(fa.right, fb.right)
    assert np.array_equal(fa.person_id, fb.person_id) and np.array_equal(a.positions, b.positions, equal_nan=True)
    assert not np.array_equal(fa.left, fc.left) and not np.allclose(a.positions[EMPTY:], c.positions[EMPTY:])
    oa = a.observations(EMPTY + 2, np.random.default_rng(3))
    ob = b.observations(EMPTY + 2, np.random.default_rng(3))
    assert all(np.array_equal(x, y) for x, y in zip(oa, ob))


def test_people_drawn_where_they_project(crossing):
    cam = crossing.camera
    for k in (EMPTY, EMPTY + 60, EMPTY + 120):
        f = crossing[k]
        for p, pos in enumerate(f.truth.position):
            mask = f.person_id == p
            if mask.sum() < 30:
                continue
            # hidden-surface removal: the pixel of the person's centre shows the person or a
            # person in front of it
            u, v = np.rint(cam.project(pos)[:2]).astype(int)
            q = f.person_id[v, u]
            assert q == p or (q >= 0 and f.depth[v, u] < pos[2] - 100.0), (k, p, q)
            rows, cols = np.nonzero(mask)
            assert cols.min() - 1 <= u <= cols.max() + 1
            # the person's top row is the top of its head (where no one stands in front)
            height = crossing.persons[p].height
            tu, tv = cam.project(crossing.rig.to_camera(f.truth.position_world[p] + [0, 0, height / 2]))[:2]
            if f.person_id[int(round(tv)) + 2, int(round(tu))] in (-1, p):
                assert rows.min() == pytest.approx(tv, abs=3.0)
            # the depth image puts each pixel of the person on the person's body: within its
            # radius of the body's vertical axis and between its feet and the top of its head
            z = f.depth[mask].astype(np.float64)
            xyz = np.column_stack([(cols - cam.cx) / cam.f * z, (rows - cam.cy) / cam.f * z, z])
            w = crossing.rig.to_world(xyz)
            base = f.truth.position_world[p] - [0.0, 0.0, height / 2]
            per = crossing.persons[p]
            r = np.linalg.norm(w[:, :2] - base[:2], axis=1)
            assert r.max() <= max(per.half_width, per.half_depth) + 2.0
            assert w[:, 2].min() >= base[2] - 2.0 and w[:, 2].max() <= base[2] + height + 2.0


def subpixel_disparity(left, right, row, col, half):
    """The disparity of the (2 half + 1)^2 patch of ``left`` at (row, col) found in ``right`` on the
    same rows by normalised cross-correlation, with a parabola through the best three scores."""
    tpl = left[row - half : row + half + 1, col - half : col + half + 1]
    lo = max(col - half - 40, 0)
    strip = right[row - half : row + half + 1, lo : col + half + 1]
    s = cv2.matchTemplate(strip, tpl, cv2.TM_CCOEFF_NORMED)[0]
    i = int(np.argmax(s))
    off = 0.0
    if 0 < i < len(s) - 1:
        den = s[i - 1] - 2 * s[i] + s[i + 1]
        off = 0.5 * (s[i - 1] - s[i + 1]) / den if den != 0 else 0.0
    return (col - half) - (lo + i + off), s[i]


def test_floor_disparity_is_b_f_over_z(crossing):
    f = crossing[0]  # no people
    cam = crossing.camera
    errs = []
    for row in (120, 160, 200, 225):
        for col in (60, 160, 260):
            d, score = subpixel_disparity(f.left, f.right, row, col, 7)
            assert score > 0.8
            errs.append(d - cam.b * cam.f / f.depth[row, col])
    assert np.abs(errs).max() < 0.5, errs


def test_person_disparity_is_b_f_over_z():
    sc = scene("merging", np.random.default_rng(2), empty_frames=0, frames=40, supersample=1)  # full size
    f = sc[30]
    cam = sc.camera
    checked = 0
    for p in range(len(sc.persons)):
        mask = f.person_id == p
        u, v, _ = np.rint(cam.project(f.truth.position[p])).astype(int)
        if not mask[v - 6 : v + 7, u - 6 : u + 7].all():
            continue  # the centre is near the person's edge or occluded
        d, score = subpixel_disparity(f.left, f.right, v, u, 6)
        assert score > 0.7
        assert d == pytest.approx(cam.b * cam.f / f.depth[v, u], abs=0.5)
        checked += 1
    assert checked >= 2


def test_group_truth_is_the_members_mean(crossing, merging, stairs):
    for sc in (crossing, merging, stairs):
        for k in (EMPTY, len(sc) // 2, len(sc) - 1):
            t = sc.truth(k)
            assert len(t.group_ids) >= 1
            for g, m, v in zip(t.group_ids, t.group_mean, t.group_velocity):
                assert m == pytest.approx(t.position[t.group == g].mean(axis=0))
                assert v == pytest.approx(t.velocity[t.group == g].mean(axis=0))
            assert sc.rig.to_camera(t.position_world) == pytest.approx(t.position)
        # velocity (mm/frame) = the positions' central difference
        p = sc.positions
        fd = (p[EMPTY + 2 :] - p[EMPTY:-2]) / 2.0
        assert np.abs(fd - sc.velocities[EMPTY + 1 : -1]).max() < 1.0  # speeds ~25 mm/frame
        # walking speed 0.9-1.5 m/s on the floor
        speed = np.linalg.norm(sc.velocities[EMPTY + 5 : EMPTY + 40], axis=-1).mean() * FPS
        assert 800.0 < speed < 1600.0, speed


def test_people_size_and_ground(crossing, stairs):
    for per in crossing.persons + stairs.persons:
        assert 1500 <= per.height <= 1900 and 400 <= 2 * per.half_width <= 500
    w = crossing.positions_world[EMPTY:]
    heights = np.array([per.height for per in crossing.persons])
    assert np.abs(w[..., 2] - heights / 2).max() < 20.0  # on the floor, with a little bob
    # stairs: the group walks away from the camera and climbs (10 steps of 170 mm from Y = 6 m)
    ws = stairs.positions_world
    assert ws[-1, :, 1].mean() > 7000.0 and ws[-1, :, 2].mean() - ws[EMPTY, :, 2].mean() > 400.0
    assert (np.diff(ws[EMPTY:, :, 1], axis=0) > 0).mean() > 0.95


def test_crossing_groups_pass_each_other(crossing):
    w = crossing.positions_world
    g = crossing.groups[EMPTY]
    assert sorted(np.bincount(g)) == [2, 3]
    xa, xb = w[:, g == 0, 0].mean(axis=1), w[:, g == 1, 0].mean(axis=1)
    assert xa[EMPTY] < -2000 and xb[EMPTY] > 2000 and xa[-1] > 1000 and xb[-1] < -1000
    kc = EMPTY + int(2.5 * FPS)
    assert abs(xa[kc] - xb[kc]) < 200.0
    # group 1 behind group 0, their image columns overlap when crossing: partial occlusion
    assert w[kc, g == 1, 1].min() > w[kc, g == 0, 1].max() + 400.0
    f = crossing[kc]
    cols = [np.nonzero(np.isin(f.person_id, np.flatnonzero(g == i)))[1] for i in (0, 1)]
    assert max(cols[0].min(), cols[1].min()) < min(cols[0].max(), cols[1].max())
    assert (crossing.groups[EMPTY:] == g).all()  # memberships never change


def test_merging_truth(merging):
    k = merging.merge_frame
    assert merging.merged_group == 2
    assert 2.2 <= (k - EMPTY) / FPS < 2.2 + 1 / FPS
    assert not (merging.groups[:k] == 2).any() and (merging.groups[k:] == 2).all()
    g0 = merging.groups[EMPTY]
    assert sorted(np.bincount(g0)) == [2, 3]
    w = merging.positions_world
    gap = lambda j: np.linalg.norm(w[j, g0 == 0, :2].mean(0) - w[j, g0 == 1, :2].mean(0))  # noqa: E731
    assert gap(EMPTY) > 4000.0 and gap(k) < 1800.0 and gap(len(merging) - 1) < 1800.0
    # after the merge the five walk on as one: away from the camera, together
    t = merging.truth(len(merging) - 1)
    assert list(t.group_ids) == [2]
    assert np.linalg.norm(t.position_world[:, :2] - t.position_world[:, :2].mean(0), axis=1).max() < 1500.0
    assert merging.velocities[-1, :, 2].mean() > 10.0  # moving away (camera z grows)
    assert small("crossing", frames=EMPTY + 2).merge_frame is None


def test_observations_on_visible_surfaces(crossing):
    k = EMPTY + int(2.5 * FPS)
    xyz, vel, pid = crossing.observations(k, np.random.default_rng(0), sigma_uv=0.0, sigma_d=0.0, p_lost=0.0,
                                          points_per_person=100)  # fmt: skip
    assert xyz.shape == vel.shape == (len(pid), 3) and pid.dtype == np.int64
    assert 0 < len(pid) < 500  # some lost to occlusion
    assert np.abs(vel - crossing.velocities[k][pid]).max() < 1e-6
    w = crossing.rig.to_world(xyz)
    base = crossing.positions_world[k][pid] - [[0, 0, per.height / 2] for per in np.array(crossing.persons)[pid]]
    r = np.linalg.norm(w[:, :2] - base[:, :2], axis=1)
    assert (r <= 260.0).all() and (w[:, 2] >= base[:, 2] - 1e-6).all()
    # the kept points are the ones the renderer shows: their left-image pixel is their person's
    f = crossing[k]
    uv = np.rint(crossing.camera.project(xyz)[:, :2]).astype(int)
    near = np.stack([f.person_id[uv[:, 1] + dv, uv[:, 0] + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    # up to points visible only between pixel centres (at occluding edges, a 160 px tall scene)
    assert (near == pid[:, None]).any(axis=1).mean() > 0.93
    # the person nearest the camera is hidden by no one; the others lose points to occlusion
    front = int(np.argmin(crossing.positions_world[k, :, 1]))
    assert (pid == front).sum() >= 95 and len(pid) < 0.8 * 500


def test_observation_noise_statistics(merging):
    k, s_uv, s_d, window = EMPTY + 40, 0.3, 0.2, 4
    true, noisy = [], []
    for seed in range(6):
        true.append(merging.observations(k, np.random.default_rng(seed), sigma_uv=0.0, sigma_d=0.0, window=window,
                                         points_per_person=200))  # fmt: skip
        noisy.append(merging.observations(k, np.random.default_rng(seed), sigma_uv=s_uv, sigma_d=s_d, window=window,
                                          points_per_person=200))  # fmt: skip
    t = [np.concatenate([a[i] for a in true]) for i in range(3)]
    n = [np.concatenate([a[i] for a in noisy]) for i in range(3)]
    assert np.array_equal(t[2], n[2]) and len(t[2]) > 2000
    cam = merging.camera
    res = cam.project(n[0]) - cam.project(t[0])
    assert res[:, 0].std() == pytest.approx(s_uv, rel=0.1) and res[:, 2].std() == pytest.approx(s_d, rel=0.1)
    assert abs(res.mean(axis=0)).max() < 0.03
    # depth noise grows as z^2: normalised by z^2 / (b f) it is the disparity noise
    z = t[0][:, 2]
    dz = (n[0][:, 2] - z) * cam.b * cam.f / z**2
    assert dz.std() == pytest.approx(s_d, rel=0.1)
    # velocity: (n_k - n_{k-w}) / w, two independent draws
    dv = (n[1][:, 2] - t[1][:, 2]) * cam.b * cam.f / z**2
    assert dv.std() == pytest.approx(math.sqrt(2) * s_d / window, rel=0.15)


def test_observation_loss_rate(crossing):
    k = EMPTY + 10
    kept = [len(crossing.observations(k, np.random.default_rng(s), p_lost=0.0)[2]) for s in range(5)]
    half = [len(crossing.observations(k, np.random.default_rng(s), p_lost=0.5)[2]) for s in range(5)]
    assert sum(half) / sum(kept) == pytest.approx(0.5, abs=0.06)
    assert all(len(a) == 0 for a in crossing.observations(0, np.random.default_rng(0)))  # empty frame


def test_bad_input():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="expected one of"):
        scene("parade", rng)
    with pytest.raises(TypeError, match="numpy.random.Generator"):
        scene("crossing", 0)
    with pytest.raises(ValueError, match="scale"):
        scene("crossing", rng, scale=3.0)
    with pytest.raises(ValueError, match="empty_frames"):
        scene("crossing", rng, empty_frames=-1, scale=0.25)
    sc = small("crossing", frames=EMPTY + 2)
    with pytest.raises(IndexError, match="frame index"):
        sc[len(sc)]
    with pytest.raises(ValueError, match="p_lost"):
        sc.observations(EMPTY, rng, p_lost=1.5)
    with pytest.raises(ValueError, match="window"):
        sc.observations(EMPTY, rng, window=0)
    assert set(SCENES) == {"crossing", "merging", "stairs"}
