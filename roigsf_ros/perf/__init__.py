"""Speed benchmarks behind ``roigsf perf <name>``: each module has ``add_arguments`` and ``run``.

Performance goals live here (JSON plus a readable table), never in timed tests.
"""
