"""Paper 002's simulator: the depth sensor model, the rendering and the sequences' ground truth (host
code, no device)."""

import math

import numpy as np
import pytest

from gputrack.sim import DepthSensor, Hall, pedestrian_sequence
from gputrack.sim.pedestrians import CHEST, body_ellipsoids, render_people

SMALL = 0.25  # 320 x 240
QUIET = dict(sun_blobs=0, sun_transient=0.0)  # no sunlight holes


def floor_and_wall(sensor, hall=Hall()):
    """(H, W) true depth of the empty hall computed here independently, and masks of its floor and
    back-wall pixels."""
    cam = sensor.camera()
    v, u = np.mgrid[0 : sensor.height, 0 : sensor.width]
    yn = (v - cam.cy) / cam.fy
    xn = (u - cam.cx) / cam.fx
    with np.errstate(divide="ignore"):
        floor = np.where(yn > 0, hall.camera_height / yn, np.inf)
        ceil = np.where(yn < 0, -(hall.ceiling_height - hall.camera_height) / yn, np.inf)
    z = np.minimum(np.minimum(floor, ceil), hall.back_wall)
    return z, floor < hall.back_wall, (z == hall.back_wall), xn, yn


# -- sensor ------------------------------------------------------------------------------------------------
def test_sensor_intrinsics_and_scale():
    s = DepthSensor()
    cam = s.camera()
    assert s.shape == (960, 1280)
    assert math.degrees(2 * math.atan(640 / cam.fx)) == pytest.approx(59.0)
    assert math.degrees(2 * math.atan(480 / cam.fy)) == pytest.approx(46.0)
    assert (cam.cx, cam.cy) == (639.5, 479.5)
    assert (cam.depth_scale, cam.min_depth, cam.max_depth) == (1.0, 300.0, 5000.0)
    small = DepthSensor(scale=SMALL).camera()
    assert DepthSensor(scale=SMALL).shape == (240, 320)
    assert small.fx == pytest.approx(cam.fx * SMALL) and small.fy == pytest.approx(cam.fy * SMALL)
    assert DepthSensor().camera("m").max_depth == 5.0
    with pytest.raises(ValueError, match="scale"):
        DepthSensor(scale=0.0)
    with pytest.raises(ValueError, match="dropout"):
        DepthSensor(dropout=1.5)


def test_empty_scene_depth_is_the_floor_and_wall_geometry():
    sensor = DepthSensor(scale=SMALL, dropout=0.0, **QUIET)
    hall = Hall()
    truth, floor, wall, _, yn = floor_and_wall(sensor, hall)
    z = hall.depth(sensor)
    np.testing.assert_allclose(z, truth, rtol=1e-5)
    assert floor.sum() > 0.1 * floor.size and wall.sum() > 0.2 * wall.size
    d = sensor.measure(z, np.random.default_rng(1)).astype(np.float64)
    assert (d > 0).all()  # no dropout, no sun: every pixel in the sensor's readings (the wall at 6 m < 10 m)
    # a level camera 1 m above the floor: the floor's depth is 1000 / (y/z) at each pixel, +-0.29 % (+0.5 mm rounding)
    err = np.abs(d - truth)
    assert (err <= 0.0029 * truth + 0.5 + 1e-3).all()
    assert err.max() > 0.0015 * truth[err.argmax() // truth.shape[1], err.argmax() % truth.shape[1]]  # noise is there
    pts = sensor.camera().points(d * floor)  # floor points back-projected: y = 1000 mm (the camera height)
    np.testing.assert_allclose(pts[:, 1], 1000.0, rtol=0.0035)


def test_noise_statistics():
    sensor = DepthSensor(scale=0.5, dropout=0.0, **QUIET)
    z = Hall().depth(sensor)
    wall = z == 6000.0
    d = sensor.measure(z, np.random.default_rng(2)).astype(np.float64)[wall]
    rel = d / 6000.0 - 1.0
    sigma = 0.0029 / 2 * 0.8796  # N(0, 1) truncated at +-2 has std 0.8796
    assert rel.std() == pytest.approx(sigma, rel=0.05)
    assert abs(rel.mean()) < 3e-5
    assert np.abs(rel).max() <= 0.0029 + 0.5 / 6000


def test_missing_readings_statistics():
    sensor = DepthSensor(scale=0.5, dropout=0.05, **QUIET)
    z = Hall().depth(sensor)
    a = sensor.measure(z, np.random.default_rng(3)) == 0
    b = sensor.measure(z, np.random.default_rng(4)) == 0
    # binomial count of missing pixels drawn with replacement: share 1 - exp(-p) ~ p
    assert a.mean() == pytest.approx(1 - math.exp(-0.05), abs=0.003)
    assert (a & b).mean() == pytest.approx(a.mean() * b.mean(), abs=0.002)  # independent frame to frame
    near = z.copy()
    near[:10] = 200.0  # closer than 0.3 m: no reading
    near[10:20] = 12000.0  # beyond the 10 m readings
    near[20:30] = np.inf  # nothing
    c = DepthSensor(scale=0.5, dropout=0.0, **QUIET).measure(near, np.random.default_rng(5))
    assert (c[:30] == 0).all() and (c[30:] > 0).all()


def test_sunlight_holes_persist_and_survive_in_the_median_background():
    seq = pedestrian_sequence(np.random.default_rng(6), frames=10, people=1, scale=SMALL)
    bg = seq.background(30)
    assert bg.shape == (30, 240, 320) and bg.dtype == np.uint16
    often = (bg == 0).mean(axis=0) > 0.7  # random dropouts alone: 2 % a frame
    blobs = np.zeros(bg.shape[1:], bool)
    for m, (r0, c0) in seq._sun:
        blobs[r0 : r0 + m.shape[0], c0 : c0 + m.shape[1]] |= m
    assert blobs.sum() > 200
    assert often[blobs].mean() > 0.9 and often[~blobs].mean() < 0.001
    median = np.median(bg, axis=0)
    assert (median[~blobs] > 0).all()  # the median removes the random missing readings (sec. 4.1)
    quiet = pedestrian_sequence(np.random.default_rng(6), frames=10, people=1, sensor=DepthSensor(scale=SMALL, **QUIET))
    assert not ((quiet.background(30) == 0).mean(axis=0) > 0.7).any()


# -- rendering ---------------------------------------------------------------------------------------------
def test_ellipsoid_depth_is_exact_for_a_sphere():
    sensor = DepthSensor(scale=SMALL)
    r, z0 = 300.0, 3000.0
    sphere = (np.array([[0.0, 0.0, z0]]), np.eye(3)[None], np.array([[r, r, r]]))
    z, label, counts = render_people(sensor, Hall(), [(7, sphere)])
    cam = sensor.camera()
    v, u = np.nonzero(label == 7)
    d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(len(u))], axis=1)
    # first hit of the ray t d with |p - c| = r: t = (d.c - sqrt((d.c)^2 - |d|^2 (|c|^2 - r^2))) / |d|^2
    dc, dd = d[:, 2] * z0, (d * d).sum(axis=1)
    t = (dc - np.sqrt(dc * dc - dd * (z0 * z0 - r * r))) / dd
    np.testing.assert_allclose(z[v, u], t, rtol=0, atol=0.1)  # float32: within 0.1 mm up to the silhouette's edge
    radius_px = cam.fx * r / math.sqrt(z0 * z0 - r * r)  # the sphere's silhouette
    assert len(u) == pytest.approx(math.pi * radius_px**2, rel=0.05)
    assert counts[7] == (len(u), len(u))


def person(x, z, height=1700.0, heading=0.0, **kw):
    return body_ellipsoids(x, z, height, heading, 0.0, **kw)


@pytest.mark.parametrize("heading", [-math.pi / 2, 0.0], ids=["towards", "across"])
def test_person_pixels_at_the_projected_position(heading):
    sensor = DepthSensor(scale=0.5)
    cam = sensor.camera()
    x, z, h = 300.0, 3000.0, 1700.0
    depth, label, counts = render_people(sensor, Hall(), [(3, person(x, z, h, heading))])
    mine = label == 3
    assert counts[3] == (mine.sum(), mine.sum()) and mine.sum() > 2000
    u, v = cam.project(np.array([x, 1000.0 - CHEST * h, z]))  # the truth's chest-height centre
    assert mine[int(round(v)), int(round(u))]
    chest = depth[int(round(v)), int(round(u))]
    if heading < 0:  # walking towards the camera: the torso's front, 105 mm before the body's axis
        assert chest == pytest.approx(z - 105.0, abs=3.0)
    else:  # walking across: the near arm (its axis 205 mm to the side, up to 45 mm thick) hides the torso
        assert z - 250.0 <= chest <= z - 205.0
    rows = np.nonzero(mine.any(axis=1))[0]
    top = cam.fy * (1000.0 - h) / z + cam.cy  # the head's top (on the body's axis, 1.7 m up)
    assert rows.min() == pytest.approx(top, abs=3)
    pts = cam.points(np.where(mine, depth, 0))
    assert np.median(pts[:, 0]) == pytest.approx(x, abs=40)
    assert pts[:, 1].max() == pytest.approx(1000.0, abs=30)  # the feet reach the floor
    assert pts[:, 2].min() > z - 260 and pts[:, 2].max() < z + 260  # the body: 0.5 m deep with the arms
    assert (depth[~mine] == Hall().depth(sensor)[~mine]).all()


def test_nearer_people_occlude_farther_ones():
    sensor = DepthSensor(scale=0.5)
    near, far = person(0.0, 2000.0), person(100.0, 4000.0)
    depth, label, counts = render_people(sensor, Hall(), [(1, far), (2, near)])
    alone_far = render_people(sensor, Hall(), [(1, far)])
    assert counts[1][0] == (alone_far[1] == 1).sum()  # pixels alone: order-independent
    assert 0 < counts[1][1] < 0.6 * counts[1][0]  # mostly hidden behind the near person
    assert counts[2][0] == counts[2][1]
    both = (alone_far[1] == 1) & (label == 2)
    assert both.sum() == counts[1][0] - counts[1][1]
    assert (depth[both] < alone_far[0][both]).all() and (depth[both] < 2300).all()
    again = render_people(sensor, Hall(), [(2, near), (1, far)])  # the drawing order does not matter
    np.testing.assert_array_equal(again[0], depth)
    np.testing.assert_array_equal(again[1], label)


def test_bags_children_and_gait_change_the_body():
    base = person(0.0, 3000.0)
    assert len(base[0]) == 7  # head, torso, pelvis, two legs, two arms
    assert len(person(0.0, 3000.0, bag="hand")[0]) == 8 and len(person(0.0, 3000.0, bag="back")[0]) == 8
    child = person(0.0, 3000.0, height=1100.0)
    assert child[0][0, 1] > base[0][0, 1] + 500  # the head is lower (y down)
    step = body_ellipsoids(0.0, 3000.0, 1700.0, 0.0, math.pi / 2)
    assert np.abs(step[0][3:5, 0] - base[0][3:5, 0]).max() > 100  # the legs swing along the heading (+x)
    still = body_ellipsoids(0.0, 3000.0, 1700.0, 0.0, math.pi / 2, moving=False)
    np.testing.assert_allclose(still[0], base[0])
    with pytest.raises(ValueError, match="bag"):
        person(0.0, 3000.0, bag="suitcase")


# -- sequences ---------------------------------------------------------------------------------------------
def test_frame_ground_truth_is_consistent():
    seq = pedestrian_sequence(np.random.default_rng(8), frames=150, people=8, scale=SMALL)
    busy = [i for i in range(150) if len(seq.in_view(i)) >= 2][:6]
    assert busy
    by_id = {p.pid: p for p in seq.people}
    for i in busy:
        f = seq[i]
        assert f.depth.shape == f.label.shape == (240, 320) and f.depth.dtype == np.uint16
        assert set(f.ids.tolist()) <= set(seq.in_view(i).tolist())
        for k, pos, fl, pix, vis, frac in zip(f.ids, f.position, f.floor, f.pixels, f.visible, f.visibility):
            p = by_id[int(k)]
            np.testing.assert_allclose(fl, [p.xz[i, 0], 1000.0, p.xz[i, 1]])
            np.testing.assert_allclose(pos, [p.xz[i, 0], 1000.0 - CHEST * p.height, p.xz[i, 1]])
            assert (f.label == k).sum() == vis and 0 < vis <= pix and frac == vis / pix
            assert vis >= seq.min_visible * 240 * 320
        assert f.time == i / 5.0


def test_sequence_is_deterministic_for_a_seed():
    a = pedestrian_sequence(np.random.default_rng(9), frames=60, people=5, scale=0.125)
    b = pedestrian_sequence(np.random.default_rng(9), frames=60, people=5, scale=0.125)
    c = pedestrian_sequence(np.random.default_rng(10), frames=60, people=5, scale=0.125)
    i = int(np.argmax(a.in_view_counts))
    fa, fb = a[i], b[i]
    np.testing.assert_array_equal(fa.depth, fb.depth)
    np.testing.assert_array_equal(fa.position, fb.position)
    np.testing.assert_array_equal(a[i].depth, fa.depth)  # rendered again, in any order: the same frame
    np.testing.assert_array_equal(a.background(2), b.background(2))
    assert not np.array_equal(a.background(1), c.background(1))
    assert not np.array_equal(a.people[0].xz, c.people[0].xz, equal_nan=True)


def test_long_sequence_statistics():
    """Paper 002's data: 851 frames, 32 people, 0-5 in view, entering and leaving, frequent occlusion."""
    seq = pedestrian_sequence(np.random.default_rng(11), scale=0.1)
    assert len(seq) == 851 and len(seq.people) == 32
    assert seq.max_in_view == 5
    counts, first, last, occluded, passing = [], {}, {}, 0, 0
    heading = {p.pid: p.heading[0] for p in seq.people}
    for f in seq:
        counts.append(f.in_view)
        dirs = np.cos([heading[k] for k in f.ids.tolist()])
        passing += int(dirs.size > 0 and dirs.max() > 0.5 and dirs.min() < -0.5)  # walking opposite ways
        for k in f.ids.tolist():
            first.setdefault(k, f.index)
            last[k] = f.index
        occluded += int((f.visibility < 0.8).sum())
    counts = np.array(counts)
    assert counts.max() <= 5 and counts.min() == 0 and (counts >= 3).sum() > 20
    assert (counts <= seq.in_view_counts).all()
    assert len(first) == 32  # everyone is labelled in some frame
    assert sum(0 < first[k] and last[k] < 850 for k in first) >= 28  # they enter and leave the view
    assert occluded > 40 and passing > 20
    heights = np.array([p.height for p in seq.people])
    assert ((heights >= 1000) & (heights <= 1400)).any() and (heights >= 1550).any()
    assert {p.bag for p in seq.people} >= {"none", "hand"} or {p.bag for p in seq.people} >= {"none", "back"}
    assert np.bincount([p.group for p in seq.people]).max() >= 2  # some walk side by side
    assert any((~p.moving & ~np.isnan(p.xz[:, 0])).any() for p in seq.people)  # someone stops
    xs = [p.xz[~np.isnan(p.xz[:, 0])] for p in seq.people]
    assert sum(len(x) > 1 and abs(x[-1, 0] - x[0, 0]) > 2000 for x in xs) >= 28  # across the view


def test_bad_input():
    rng = np.random.default_rng(0)
    with pytest.raises(TypeError, match="Generator"):
        pedestrian_sequence(0)
    with pytest.raises(ValueError, match="frames"):
        pedestrian_sequence(rng, frames=0)
    with pytest.raises(ValueError, match="could not place"):
        pedestrian_sequence(rng, frames=10, people=40, scale=0.1)
    with pytest.raises(ValueError, match="depth_range"):
        pedestrian_sequence(rng, depth_range=(100.0, 5000.0))
    seq = pedestrian_sequence(rng, frames=5, people=1, scale=0.1)
    with pytest.raises(IndexError, match="frame index"):
        seq[5]
