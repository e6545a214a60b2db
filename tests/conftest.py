"""Test configuration: one ``device`` fixture parametrised over every backend.

Unavailable backends are skipped with their reason, unless listed in ``GPUTRACK_REQUIRE``
(comma-separated specs), which turns them into errors. The fixture is session-scoped so that
pytest groups the tests by device; a Taichi device is closed when its group ends, which lets
the next Taichi arch start in the same process.
"""

import os

import pytest

import gputrack
from gputrack.registry import specs as registry_specs

#: every backend's fixed specs, from the backend table (gputrack/registry.py)
ALL_SPECS = registry_specs()

#: the devices that run long accuracy protocols (many frames, many trials) in full: the fast local
#: backends. Every other device runs a short run of the same code path, pinned to the same bounds
#: or to the reference (keeps the suite within 10 minutes on a 2-core machine).
FULL_PROTOCOL = ("taichi:cpu", "opencl")


def deep() -> bool:
    """The deep profile (``GPUTRACK_TESTS=deep``): every tuning candidate's combination and the fuzz
    suite's every mutation, beyond the default profile that keeps the suite within its budget."""
    return os.environ.get("GPUTRACK_TESTS", "").strip().lower() == "deep"


def full_protocol(device) -> bool:
    """Whether ``device`` runs the long accuracy protocols in full (see FULL_PROTOCOL)."""
    return device.spec in FULL_PROTOCOL


def _required() -> set[str]:
    return {s.strip() for s in os.environ.get("GPUTRACK_REQUIRE", "").split(",") if s.strip()}


def _infos() -> dict:
    return {d.spec: d for d in gputrack.devices()}


def pytest_report_header(config):
    lines = ["gputrack devices:"]
    for d in gputrack.devices():
        state = f"available  {d.name}" + ("  fp64" if d.fp64 else "") if d.available else f"UNAVAILABLE  {d.reason}"
        lines.append(f"  {d.spec:<16} {state}")
    req = _required()
    if req:
        lines.append(f"  required (GPUTRACK_REQUIRE): {', '.join(sorted(req))}")
    return lines


def pytest_configure(config):
    # the groups of pytest-xdist's --dist loadgroup (pytest_collection_modifyitems); registered here
    # too, for a plain `pytest` where pytest-xdist is not installed
    config.addinivalue_line("markers", "xdist_group(name): tests that one pytest-xdist worker runs in order")
    # tests use the default launch parameters, not a tuning cache the user may have
    if "GPUTRACK_TUNING_CACHE" not in os.environ:
        import tempfile

        os.environ["GPUTRACK_TUNING_CACHE"] = os.path.join(tempfile.mkdtemp(prefix="gputrack-tests-"), "tuning.json")
    unknown = _required() - set(_infos())
    if unknown:
        raise pytest.UsageError(f"GPUTRACK_REQUIRE names unknown specs {sorted(unknown)}; known: {sorted(_infos())}")


@pytest.fixture(scope="session")
def ict():
    """The ICT face data (:func:`gputrack.models.face.load_ict`); the test is skipped, with the reason,
    where it is absent."""
    from gputrack.models.face import load_ict

    try:
        return load_ict()
    except FileNotFoundError as e:
        pytest.skip(f"the ICT face data is absent ({e}); it lives in shared/data/ict_face beside the repository, "
                    "or $GPUTRACK_DATA/ict_face")  # fmt: skip


@pytest.fixture(scope="session", params=ALL_SPECS)
def device(request):
    spec = request.param
    info = _infos()[spec]
    if not info.available:
        if spec in _required():
            pytest.fail(f"{spec} is required by GPUTRACK_REQUIRE but not available: {info.reason}", pytrace=False)
        pytest.skip(f"{spec} not available: {info.reason}")
    dev = gputrack.device(spec)
    yield dev
    if dev.backend == "taichi":
        dev.close()  # lets the next Taichi arch start in this process


def pytest_collection_modifyitems(config, items):
    """Groups for pytest-xdist's ``--dist loadgroup`` (the README's test command ``-n 2``): every test
    of one Taichi arch runs in one worker, in order, so that a worker starts each arch at most once
    (Taichi runs one arch per process); the other devices' tests and those that take no device
    ("host") are grouped per module, which lets the workers share them out."""
    for item in items:
        callspec = getattr(item, "callspec", None)
        spec = (callspec.params.get("device") if callspec is not None else None) or "host"
        group = spec if spec.startswith("taichi:") else f"{spec}:{item.module.__name__}"
        item.add_marker(pytest.mark.xdist_group(group))
