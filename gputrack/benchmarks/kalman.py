"""Batched Kalman filters: T = 1e3 .. 1e6 tracks, state n = 6, observation m = 3, D = 100 detections.

Cases per T, each timed on the device with the NumPy reference (the same op on the ``numpy``
device) in the same run:

- ``kf predict+update``: one fused ``kf_update(..., predict=(F, Q), out=(x, P, status))`` of the
  constant-velocity model (paper 001 eq. 1-3) with a position observation, in place on
  device-resident state (what a tracker does every frame); F, Q, H, R are
  :func:`gputrack.ops.kalman.shared_matrix` objects uploaded once.
- ``kf predict+update+gating``: the same plus ``mahalanobis`` of every track against 100
  detections (paper 001 eq. 8) into a preallocated (T, 100) array.
- ``ekf stereo predict+update``: the stereo EKF of paper 001 (eq. 4-6), fused likewise.

Peers at T <= --loop-max-tracks (default 1e3): ``python loop`` — the textbook filter written per
track in Python/NumPy (F x, F P F^T + Q, inv(H P H^T + R), Joseph covariance; and for gating
a solve per track against the 100 detections), as trackers in the wild run one filter object per
track. The reference is skipped above --reference-max-tracks (default 1e5) for the gating case
(its (T, D, m) temporaries at T = 1e6 take gigabytes).
"""

import sys

import numpy as np

from .harness import Case, bench_main
from ..sim.problems import kalman_tracks

NAME = "kalman"
D = 100


def add_arguments(parser):
    parser.add_argument("--tracks", type=float, action="append", help="T (repeatable; default 1e3 1e4 1e5 1e6)")
    parser.add_argument("--loop-max-tracks", type=float, default=1e3, help="largest T timed with the Python loop peer")
    parser.add_argument("--reference-max-tracks", type=float, default=1e5, help="largest T for the gating reference")


def _textbook(x, P, F, Q, z, H, R, det=None):
    """One frame of the textbook filter, one track at a time (the peer)."""
    eye = np.eye(F.shape[0])
    out = []
    for t in range(x.shape[0]):
        xp = F @ x[t]
        Pp = F @ P[t] @ F.T + Q
        if det is not None:  # gate against every detection with the predicted state
            Hx = H @ xp
            S = H @ Pp @ H.T + R
            r = det - Hx
            out.append(np.einsum("di,di->d", r, np.linalg.solve(S, r.T).T))
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        x[t] = xp + K @ (z[t] - H @ xp)
        A = eye - K @ H
        P[t] = A @ Pp @ A.T + K @ R @ K.T
    return out


def _stereo_textbook(x, P, F, Q, z, R, f, b):
    eye = np.eye(6)
    for t in range(x.shape[0]):
        xp = F @ x[t]
        Pp = F @ P[t] @ F.T + Q
        iz = 1.0 / xp[4]
        h = np.array([f * xp[0] * iz, f * xp[2] * iz, f * b * iz])
        J = np.zeros((3, 6))
        J[0, 0] = J[1, 2] = f * iz
        J[0, 4], J[1, 4], J[2, 4] = -f * xp[0] * iz * iz, -f * xp[2] * iz * iz, -f * b * iz * iz
        K = Pp @ J.T @ np.linalg.inv(J @ Pp @ J.T + R)
        x[t] = xp + K @ (z[t] - h)
        A = eye - K @ J
        P[t] = A @ Pp @ A.T + K @ R @ K.T


def cases(device, args):
    from ..registry import device as get_device
    from ..ops.kalman import ekf_update_stereo, kf_update, mahalanobis, shared_matrix

    ref = get_device("numpy")
    rng = np.random.default_rng(0)
    sizes = [int(t) for t in (args.tracks or [1e3, 1e4, 1e5, 1e6])]
    out = []
    f, b = 480.0, 0.12
    for T in sizes:
        F, Q, H, R, x0, P0, z, det = kalman_tracks(T, rng, D)
        Fs, Qs, Hs, Rs = (shared_matrix(device, a) for a in (F, Q, H, R))
        Fr, Qr, Hr, Rr = (shared_matrix(ref, a) for a in (F, Q, H, R))
        x, P, zd, detd = device.asarray(x0), device.asarray(P0), device.asarray(z), device.asarray(det)
        st = device.empty((T,), np.uint8)
        d2 = device.empty((T, D), np.float32)
        xr, Pr, str_ = x0.copy(), P0.copy(), np.empty(T, np.uint8)
        d2r = np.empty((T, D), np.float32)
        zs = np.stack([f * x0[:, 0] / x0[:, 4], f * x0[:, 2] / x0[:, 4], f * b / x0[:, 4]], 1).astype(np.float32)
        zsd = device.asarray(zs)
        xs, Ps = device.asarray(x0), device.asarray(P0)
        xsr, Psr = x0.copy(), P0.copy()
        Rst = shared_matrix(device, np.diag([1.0, 1.0, 0.1]))
        Rstr = shared_matrix(ref, np.diag([1.0, 1.0, 0.1]))

        def step(x=x, P=P, zd=zd, st=st, Fs=Fs, Qs=Qs, Hs=Hs, Rs=Rs):
            return kf_update(device, x, P, zd, Hs, Rs, predict=(Fs, Qs), out=(x, P, st))

        def step_ref(xr=xr, Pr=Pr, z=z, s=str_, Fr=Fr, Qr=Qr, Hr=Hr, Rr=Rr):
            return kf_update(ref, xr, Pr, z, Hr, Rr, predict=(Fr, Qr), out=(xr, Pr, s))

        def gated(step=step, x=x, P=P, detd=detd, d2=d2, Fs=Fs, Qs=Qs, Hs=Hs, Rs=Rs):
            # gating uses the predicted state: predict+update fused, then distances of the new state
            step()
            return mahalanobis(device, x, P, Hs, Rs, detd, out=d2)

        def gated_ref(step_ref=step_ref, xr=xr, Pr=Pr, det=det, d2r=d2r, Hr=Hr, Rr=Rr):
            step_ref()
            return mahalanobis(ref, xr, Pr, Hr, Rr, det, out=d2r)

        def stereo(xs=xs, Ps=Ps, zsd=zsd, st=st, Fs=Fs, Qs=Qs, Rst=Rst):
            return ekf_update_stereo(device, xs, Ps, zsd, Rst, f=f, b=b, predict=(Fs, Qs), out=(xs, Ps, st))

        def stereo_ref(xsr=xsr, Psr=Psr, zs=zs, s=str_, Fr=Fr, Qr=Qr, Rstr=Rstr):
            return ekf_update_stereo(ref, xsr, Psr, zs, Rstr, f=f, b=b, predict=(Fr, Qr), out=(xsr, Psr, s))

        def e2e(x0=x0, P0=P0, z=z, Fs=Fs, Qs=Qs, Hs=Hs, Rs=Rs):
            r = kf_update(device, x0, P0, z, Hs, Rs, predict=(Fs, Qs))
            return [device.to_numpy(a) for a in r]

        loop = T <= args.loop_max_tracks
        F64, Q64, H64, R64 = (a.astype(np.float64) for a in (F, Q, H, R))
        xl, Pl = x0.astype(np.float64), P0.astype(np.float64)
        Rs64 = np.diag([1.0, 1.0, 0.1])
        params = {"T": T, "n": 6, "m": 3, "dtype": "float32"}
        out.append(
            Case(
                f"kf predict+update T={T:.0e}",
                run=step,
                reference=step_ref,
                end_to_end=e2e,
                peers={"python loop": lambda a=(xl, Pl, F64, Q64, z, H64, R64): _textbook(*a)} if loop else {},
                params=params,
            )
        )
        out.append(
            Case(
                f"kf predict+update+gating T={T:.0e}",
                run=gated,
                reference=gated_ref if T <= args.reference_max_tracks else None,
                peers={"python loop": lambda a=(xl, Pl, F64, Q64, z, H64, R64, det): _textbook(*a)} if loop else {},
                params={**params, "D": D},
            )
        )
        xsl, Psl = x0.astype(np.float64), P0.astype(np.float64)
        out.append(
            Case(
                f"ekf stereo predict+update T={T:.0e}",
                run=stereo,
                reference=stereo_ref,
                peers={"python loop": lambda a=(xsl, Psl, F64, Q64, zs, Rs64, f, b): _stereo_textbook(*a)}
                if loop
                else {},
                params=params,
            )
        )
    return out


if __name__ == "__main__":
    sys.exit(bench_main(sys.modules[__name__]))
