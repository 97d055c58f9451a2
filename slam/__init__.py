"""Monocular visual SLAM with TerraSLAM's hierarchical acceleration (issue 4).

Layout (one job per module):
  types.py      boundary values (Frame, AttitudePrior, SlamPose, MapUpdate, ...)
  config.py     SlamConfig (section ``slam``)
  system.py     SlamSystem: track() in the caller's thread, poll_map_updates(), map_points(), keyframe_poses()
  features.py   OpenCV ORB spread over a 16x16 grid (CPU path) and the backend switch
  torch_orb.py  patch-parallel ORB-style features in torch (§5.1, GA)
  matching.py   Hamming brute force with ratio test; projection-guided matching
  geometry.py   transforms, projection, triangulation, H-vs-E two-view init, Sim(3) Umeyama/RANSAC
  tracking.py   motion model, local-map tracking, PnP + pose-only refinement, keyframe decision,
                state machine (initializing/ok/lost/relocalized), relocalization, reset
  map.py        keyframes + map points (one lock, background threads only) and the tracker's snapshot
  mapping.py    background thread: triangulation, culling, local BA (PLM), loop closing (full/RLC)
  ba.py         gtsam bundle adjustment, run in a worker process (gtsam holds the GIL)
  plm.py        Eq. 4 reliable region, PLM window, Algorithm 1 control flow
  place.py      place recognition: bag of binary words, inverted file, L1 score (nothing downloaded)
  vocab.py      the ORB vocabulary (tree, tf-idf), its file slam/data/orb_vocab.npz; vocab_train.py trains it
  place_eval.py `python -m companion.slam_bench.place_eval bench|recall`: place-recognition timings and recognition figures
  bench.py      `python -m companion.slam_bench` on the simulator's scenarios
"""
