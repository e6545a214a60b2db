"""The tuning cache: read, write, corruption, staleness, and the choice the ops get."""

import json

import pytest

import gputrack
from gputrack import tuning


def make_tunable(op="demo", candidates=None, runs=None):
    runs = runs if runs is not None else []

    def problem(device, size, params):
        def run():
            runs.append(params["wg"])
            # a slower candidate sleeps longer: wg=64 is the fastest here
            import time

            time.sleep(0.0002 if params["wg"] == 64 else 0.002)

        return run

    return tuning.Tunable(
        op=op,
        backend="numpy",
        candidates=candidates or {"wg": [32, 64, 128]},
        default={"wg": 128},
        sizes=({"B": 1500, "N": 128},),
        problem=problem,
    )


@pytest.fixture
def numpy_device():
    return gputrack.device("numpy")


def test_size_bucket_rounds_up_to_powers_of_two():
    assert tuning.size_bucket({"N": 128, "B": 1500}) == "B=2048,N=128"
    assert tuning.size_bucket({"B": 1}) == "B=1"
    assert tuning.size_bucket({"B": 129}) == "B=256"


def test_tune_stores_fastest_and_choose_uses_it(tmp_path, monkeypatch, numpy_device):
    monkeypatch.setenv("GPUTRACK_TUNING_CACHE", str(tmp_path / "t.json"))
    t = make_tunable()
    assert tuning.choose(numpy_device, t, {"B": 1500, "N": 128}) == {"wg": 128}  # default
    chosen = tuning.tune(numpy_device, t, min_time=0.005)
    assert chosen == {"B=2048,N=128": {"wg": 64}}
    assert tuning.choose(numpy_device, t, {"B": 1500, "N": 128}) == {"wg": 64}
    assert tuning.choose(numpy_device, t, {"B": 1025, "N": 100}) == {"wg": 64}  # same bucket
    assert tuning.choose(numpy_device, t, {"B": 10, "N": 128}) == {"wg": 128}  # other bucket: default
    doc = json.loads((tmp_path / "t.json").read_text())
    (key,) = doc["devices"]
    assert key.startswith("numpy|NumPy")
    assert set(doc["devices"][key]["demo"]["B=2048,N=128"]["timings_ms"]) == {
        json.dumps({"wg": w}) for w in (32, 64, 128)
    }


def test_corrupt_cache_is_ignored_with_warning(tmp_path, monkeypatch, numpy_device):
    path = tmp_path / "t.json"
    path.write_text("{not json")
    monkeypatch.setenv("GPUTRACK_TUNING_CACHE", str(path))
    with pytest.warns(RuntimeWarning, match="ignoring the tuning cache"):
        assert tuning.choose(numpy_device, make_tunable(), {"B": 1500, "N": 128}) == {"wg": 128}


def test_stale_or_invalid_entries_are_ignored_with_warning(tmp_path, numpy_device):
    cache = tuning.TuningCache(tmp_path / "t.json")
    t = make_tunable()
    cache.put(numpy_device, t, {"B": 1500, "N": 128}, {"wg": 64})
    cache.save()
    assert tuning.TuningCache(tmp_path / "t.json").get(numpy_device, t, {"B": 1500, "N": 128}) == {"wg": 64}
    # the candidate grid (or kernel source) changed: the entry is stale
    t2 = make_tunable(candidates={"wg": [32, 64, 128, 256]})
    with pytest.warns(RuntimeWarning, match="stale"):
        assert tuning.TuningCache(tmp_path / "t.json").get(numpy_device, t2, {"B": 1500, "N": 128}) is None
    # a value outside the candidates
    doc = json.loads((tmp_path / "t.json").read_text())
    entry = next(iter(doc["devices"].values()))["demo"]["B=2048,N=128"]
    entry["params"] = {"wg": 48}
    (tmp_path / "t.json").write_text(json.dumps(doc))
    with pytest.warns(RuntimeWarning, match="wg=48 is not one of"):
        assert tuning.TuningCache(tmp_path / "t.json").get(numpy_device, t, {"B": 1500, "N": 128}) is None


def test_wrong_version_is_ignored(tmp_path, numpy_device):
    (tmp_path / "t.json").write_text(json.dumps({"version": 99, "devices": {}}))
    with pytest.warns(RuntimeWarning, match="expected a version 1 tuning cache"):
        assert tuning.TuningCache(tmp_path / "t.json").get(numpy_device, make_tunable(), {"B": 1}) is None
