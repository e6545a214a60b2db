"""Benchmark definitions, one module per primitive or tracker (run by ``perf/`` and ``gputrack bench``).

Each module has ``NAME``, ``cases(device, args) -> list[gputrack.benchmark.Case]``, optionally
``add_arguments(parser)``, and ends with::

    if __name__ == "__main__":
        sys.exit(bench_main(sys.modules[__name__]))
"""
