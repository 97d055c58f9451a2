"""``python -m companion.slam_bench``: the SLAM benchmark's command line (companion/slam_bench/cli.py)."""
from companion.slam_bench.cli import main

main()
