"""The benchmarks a user runs, each a module run from the repository root.

    python -m benchmarks.selection     # selection core: seconds per stage, peak memory
    python -m benchmarks.rasterizer    # CPU rasterizer forward/backward
    python -m benchmarks.recon         # reconstruction time to quality
    python -m benchmarks.fidelity      # fidelity of the stored free views
    python -m benchmarks.loader        # training-shard loader throughput
    python -m benchmarks.ingest        # scene ingestion on the shared real scenes
    python -m benchmarks.masks         # object masks on a turntable capture
    python -m benchmarks.fixer_speed   # fixer network inference speed
    python -m benchmarks.store_diff A B  # two stores' published outputs equal
"""
