"""Developer tools run from the repository, not installed with ``parproj_ros``.

``python -m tools.bench``: speed and memory of the normalization (``bench/run.sh`` runs it and
rewrites ``bench/BENCHMARKS.md``). ``python -m tools.longrun``: the live node fed one bag for
hours. Both share :mod:`tools.harness` (memory and CPU sampling, JSON cleaning, machine facts) and
run the node with :mod:`parproj_ros.ros.live`.
"""
