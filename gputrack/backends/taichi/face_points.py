"""Taichi: the projection of face hypotheses (gputrack/ops/face_points.py) in float32, one launch:
a thread per hypothesis poses (its Rodrigues rotation by :func:`trig.sincos32`) and projects the
model's K points. On the CPU arch the loop runs on the calling thread: ~0.1-0.2 ms for the face
tracker's 1000 hypotheses, where waking the thread pool cost more than it saved: the tracker's
sample stage 0.63-0.74 -> 0.51-0.57 ms and its whole frame 5.2-5.3 -> 4.1-4.7 ms (medians of 183
frames, three runs of each in turn, 2026-12-06)."""

from ...uploads import constant
from .launch import launch
from .runtime import current_arch, ti
from .trig import sincos32

F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
F3 = ti.types.ndarray(dtype=ti.f32, ndim=3)


@ti.kernel
def _project(states: F2, model: F3, cam: F1, points: F3, facing: F1, serial: ti.template()):
    fx, fy, cx, cy, near, clip = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5]
    K, D = model.shape[0], model.shape[2] - 1
    if ti.static(serial):
        ti.loop_config(serialize=True)
    for n in range(states.shape[0]):
        r = ti.Vector([states[n, 0], states[n, 1], states[n, 2]])
        t = ti.Vector([states[n, 3], states[n, 4], states[n, 5]])
        # R = I + a [r]x + b [r]x^2, a = sin th / th, b = (1 - cos th) / th^2 (series below 1e-3)
        t2 = r.dot(r)
        th = ti.sqrt(t2)
        small = th < 1e-3
        ts = ti.select(small, 1.0, th)
        sh, ch = sincos32(0.5 * ts)  # sin th = 2 sh ch, 1 - cos th = 2 sh^2 (no cancellation)
        a = ti.select(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, 2.0 * sh * ch / ts)
        b = ti.select(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 2.0 * sh * sh / (ts * ts))
        Kx = ti.Matrix([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
        R = ti.Matrix.identity(ti.f32, 3) + a * Kx + b * (Kx @ Kx)
        for k in range(K):
            X = ti.Vector([model[k, 0, 0], model[k, 1, 0], model[k, 2, 0]])
            for d in range(D):  # eq. 11
                X += ti.Vector([model[k, 0, 1 + d], model[k, 1, 1 + d], model[k, 2, 1 + d]]) * states[n, 6 + d]
            Y = R @ X + t
            iz = 1.0 / ti.max(Y[2], near)  # eq. 5
            points[n, k, 0] = ti.min(ti.max(fx * Y[0] * iz + cx, -clip), clip)
            points[n, k, 1] = ti.min(ti.max(fy * Y[1] * iz + cy, -clip), clip)
        facing[n] = (R[0, 2] * t[0] + R[1, 2] * t[1] + R[2, 2] * t[2]) / ti.max(ti.sqrt(t.dot(t)), 1e-9)


def project_faces(device, states, model, cam, points, facing):
    serial = current_arch() == "cpu"  # see the module docstring
    launch(_project, (states.buffer, model.buffer, constant(device, cam).buffer, points.buffer, facing.buffer),
           (serial,))
