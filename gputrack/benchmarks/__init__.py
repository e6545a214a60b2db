"""Benchmark definitions, one module per primitive or tracker (run by ``perf/`` and ``gputrack bench``),
and the harness that times them (:mod:`.harness`).

Each definition module has ``NAME``, ``cases(device, args) -> list[gputrack.benchmarks.harness.Case]``, optionally
``add_arguments(parser)``, and ends with::

    if __name__ == "__main__":
        sys.exit(bench_main(sys.modules[__name__]))
"""
