"""The self-tests fail on a wrong kernel, and the doctor (``gputrack doctor``, gputrack/doctor.py)
reports its failures: a missing device, a failing self-test, a self-test process that dies."""

import dataclasses
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import gputrack
from conftest import full_protocol
from gputrack import selftest
from gputrack.device import DeviceArray

ROOT = Path(__file__).resolve().parent.parent

#: the ops each self-test runs (module, function): each made wrong in turn must fail the check
OPS_OF_CHECK = {
    "kinematics": [("kinematics", "forward_kinematics")],
    "template": [("template", "rgbd_cost"), ("ncc", "patch_ncc")],
    "particles": [("particles", "sample_around"), ("particles", "best_k")],
    "pf_stage": [("pf", "pf_stage")],
    "pose_residuals": [("pose_residuals", "pose_residuals")],
    "lm": [("lm", "lm_solve"), ("lm", "least_squares")],
    "kalman": [("kalman", "kf_predict"), ("kalman", "kf_update"), ("kalman", "ekf_update_stereo"),
               ("kalman", "mahalanobis")],  # fmt: skip
    "gating": [("gating", "gate_pairs"), ("rows", "scatter_rows")],
    "point_groups": [("point_groups", "assign_points")],
    "stereo": [("stereo", "stereo_match")],
    "background": [("background", "background_median"), ("background", "foreground_mask"),
                   ("background", "update_background"), ("depth_points", "depth_points")],  # fmt: skip
    "clusters": [("clusters", "dbscan")],
    "face_bundle": [("face_bundle", "landmark_residuals")],
    "face_points": [("face_points", "project_faces")],
    "face_relocate": [("face_relocate", "relocate_points")],
}


def _bump(a: np.ndarray) -> np.ndarray:
    """A wrong result of the same shape and dtype: floats moved by 0.5 + 10%, integers by 1, 0/1 flags flipped."""
    if a.dtype.kind == "f":
        return (a + (0.5 + 0.1 * np.abs(a))).astype(a.dtype)
    if a.dtype.kind == "b" or a.dtype == np.uint8:
        return (1 - a.astype(np.int64)).astype(a.dtype)
    return (a + 1).astype(a.dtype)


def _perturb(result, device):
    """Make every array of ``result`` (on ``device``, or host arrays) wrong, in place."""
    if isinstance(result, DeviceArray):
        if result.size:
            device.asarray(_bump(gputrack.to_numpy(result)), out=result)
    elif isinstance(result, np.ndarray):
        if result.size and result.flags.writeable:
            result[...] = _bump(result)
    elif dataclasses.is_dataclass(result):
        for f in dataclasses.fields(result):
            _perturb(getattr(result, f.name), device)
    elif isinstance(result, (tuple, list)):
        for r in result:
            _perturb(r, device)


def _wrong_op(monkeypatch, device, module: str, name: str) -> None:
    """Replace gputrack.ops.<module>.<name> by one whose results on ``device`` are wrong (a
    deliberately wrong kernel, as the self-tests see it); the reference's stay right."""
    mod = __import__(f"gputrack.ops.{module}", fromlist=[name])
    real = getattr(mod, name)

    def wrong(*args, **kw):
        dev = kw.get("device", args[0] if args else None)
        out = real(*args, **kw)
        if dev is device:
            _perturb(out, device)
        return out

    monkeypatch.setattr(mod, name, wrong)


def test_every_self_test_has_its_ops_listed():
    assert [name for name, _ in selftest.CHECKS] == ["arrays", *OPS_OF_CHECK]


@pytest.mark.parametrize("check", list(OPS_OF_CHECK))
def test_self_test_fails_on_a_wrong_kernel(device, monkeypatch, check):
    """Each self-test passes on the device, and fails (AssertionError naming the op) when one of its
    ops gives wrong results there: every op of the check on the fast local devices, the first one
    elsewhere."""
    if device.backend == "numpy":
        pytest.skip("numpy is the reference the self-tests compare with")
    fn = dict(selftest.CHECKS)[check]
    fn(device)  # passes as it is
    ops = OPS_OF_CHECK[check] if full_protocol(device) else OPS_OF_CHECK[check][:1]
    for module, name in ops:
        with monkeypatch.context() as m:
            _wrong_op(m, device, module, name)
            with pytest.raises(AssertionError) as e:
                fn(device)
        assert str(e.value), f"{check}: an empty failure message with {name} wrong"
        rows = None
        with monkeypatch.context() as m:
            _wrong_op(m, device, module, name)
            m.setattr(selftest, "CHECKS", [(check, fn)])
            rows = selftest.run(device)
        assert [(r["check"], r["ok"]) for r in rows] == [(check, False)], rows
        assert rows[0]["detail"].startswith("AssertionError: "), rows


def test_arrays_self_test_fails_on_a_wrong_upload(device, monkeypatch):
    if device.backend == "numpy":
        pytest.skip("numpy has no upload")
    real = device.asarray
    monkeypatch.setattr(device, "asarray", lambda a, *args, **kw: real(_bump(np.asarray(a)), *args, **kw))
    with pytest.raises(AssertionError, match="float32 round trip differs"):
        selftest.check_arrays(device)


# -- the doctor's failure paths -------------------------------------------------------------------------
def _doctor(tmp_path, *argv, site: str = ""):
    """``python -m gputrack.cli doctor ARGV --json`` with ``site`` as a sitecustomize module (run at
    the start of the doctor and of its self-test processes): (process, report)."""
    env = None
    if site:
        (tmp_path / "sitecustomize.py").write_text(textwrap.dedent(site))
        import os

        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    report = tmp_path / "report.json"
    proc = subprocess.run([sys.executable, "-m", "gputrack.cli", "doctor", *argv, "--json", str(report)],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)  # fmt: skip
    return proc, json.loads(report.read_text()) if report.exists() else None


def test_doctor_reports_a_failing_self_test(tmp_path):
    """A wrong OpenCL kernel (forward kinematics moved by 0.5): the doctor prints the failure, lists it
    as a problem and exits 1."""
    if not {d.spec: d for d in gputrack.devices()}["opencl"].available:
        pytest.skip("no OpenCL device")
    site = """
        import gputrack.backends.opencl.kinematics as k
        from gputrack import selftest

        real = k.forward_kinematics

        def wrong(device, chain, params, out):
            r = real(device, chain, params, out)
            device.asarray(gputrack.to_numpy(out) + 0.5, out=out)
            return r

        import gputrack
        k.forward_kinematics = wrong
        selftest.CHECKS = [c for c in selftest.CHECKS if c[0] in ("arrays", "kinematics")]
    """
    proc, report = _doctor(tmp_path, "--device", "opencl", site=site)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert report["problems"] == ["opencl: self-test kinematics failed"], report["problems"]
    rows = report["selftests"]["opencl"]
    assert [(r["check"], r["ok"]) for r in rows] == [("arrays", True), ("kinematics", False)], rows
    assert "forward_kinematics (float32) differs from the reference by 0.5" in rows[1]["detail"]
    assert "FAILED AssertionError: forward_kinematics (float32) differs" in proc.stdout
    assert proc.stdout.rstrip().endswith("opencl: self-test kinematics failed")


def test_doctor_reports_a_self_test_process_that_dies_and_a_missing_device(tmp_path):
    """A self-test process that dies (exit 3 without a report) fails its device; a required device
    that does not exist and an unknown --device are problems too."""
    site = """
        import os
        from gputrack import selftest

        def die(device):
            os._exit(3)

        selftest.run = die
    """
    proc, report = _doctor(tmp_path, "--device", "numpy", "--device", "opencl:nope", "--require", "taichi:nope",
                           site=site)  # fmt: skip
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert report["selftests"]["numpy"] == [
        {"check": "start", "ok": False, "detail": "self-test process failed (return code 3): no output", "ms": 0.0}
    ]
    assert report["problems"] == ["taichi:nope: unknown spec", "opencl:nope: unknown spec (--device)",
                                  "numpy: self-test start failed"]  # fmt: skip
    assert set(report["selftests"]) == {"numpy"} and report["builds"] == []


def test_host_doctor_is_the_package_doctor():
    proc = subprocess.run([sys.executable, "host/doctor.py", "--help"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0 and proc.stdout.startswith("usage: gputrack doctor"), proc.stdout + proc.stderr
    assert "--require" in proc.stdout and "--device SPEC" in proc.stdout


def test_doctor_hints_where_a_gpu_backend_is_not_reachable(tmp_path):
    """NVIDIA's OpenCL library without an ICD file naming it, and Vulkan without its loader, each
    give an instruction; a registered library, an OpenCL GPU or a working Vulkan give none."""
    from gputrack.device import DeviceInfo
    from gputrack.doctor import hints

    libs, icd = tmp_path / "lib", tmp_path / "vendors"
    libs.mkdir()
    icd.mkdir()
    (libs / "libnvidia-opencl.so.1").write_bytes(b"")
    (icd / "pocl.icd").write_text("libpocl.so.2\n")
    cpu_cl = DeviceInfo("opencl", "opencl", True, name="PoCL", kind="cpu")
    no_vk = DeviceInfo("taichi:vulkan", "taichi", False, reason="no Vulkan loader (libvulkan.so.1 not loadable) or ...")
    got = hints([cpu_cl, no_vk], library_dirs=[str(libs)], icd_dir=str(icd))
    assert len(got) == 2
    assert f"echo libnvidia-opencl.so.1 > {icd}/nvidia.icd" in got[0]
    assert "libvulkan1" in got[1]
    (icd / "nvidia.icd").write_text("libnvidia-opencl.so.1\n")
    assert hints([cpu_cl], library_dirs=[str(libs)], icd_dir=str(icd)) == []
    (icd / "nvidia.icd").unlink()
    gpu_cl = DeviceInfo("opencl", "opencl", True, name="NVIDIA H100", kind="gpu")
    vk = DeviceInfo("taichi:vulkan", "taichi", True, name="NVIDIA H100", kind="gpu")
    assert hints([gpu_cl, vk], library_dirs=[str(libs)], icd_dir=str(icd)) == []
    assert hints([cpu_cl], library_dirs=[str(tmp_path / "none")], icd_dir=str(icd)) == []
