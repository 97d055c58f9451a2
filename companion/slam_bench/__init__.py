"""Benchmarks and tools of ``slam/`` that fly the simulator (``companion/sim/``), kept out of
``slam/`` so that it imports nothing of ours above it (pyproject.toml, import-linter contracts):

  cli.py        `python -m companion.slam_bench` on the simulator's scenarios (tracking, ablation, memory)
  sequence.py   rendered sequences: render, cache, save for replay elsewhere, load
  runs.py       SLAM runs over a sequence and their figures
  memory.py     the long-flight memory benchmark (`python -m companion.slam_bench --memory`)
  place_eval.py `python -m companion.slam_bench.place_eval bench|recall`: place-recognition figures
  vocab_train.py `python -m companion.slam_bench.vocab_train`: trains slam/data/orb_vocab.npz
"""
