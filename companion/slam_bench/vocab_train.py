"""Train the place-recognition vocabulary shipped as slam/data/orb_vocab.npz (a development tool:
nothing here runs on the vehicle).

    python -m companion.slam_bench.vocab_train                         # defaults below, writes slam/data/orb_vocab.npz
    python -m companion.slam_bench.vocab_train --cache /tmp/vocab_desc.npz --k 16 --levels 4

Training images: frames of our simulator (``companion.sim``) on several scenarios over worlds of
seeds 1-2 (the tests and the recognition check fly seed 0), and scikit-image photos seen through
random homographies, so the words are not only the simulator's textures. The photos the tests
query with (camera, coins, moon, text, brick, grass) are left out; note that the simulator
textures its ground with some of them (companion/sim/textures.py), so sim frames hold them from
afar. ORB as the tracker extracts it (slam.features.make_orb_cpu, 1000 features).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from slam.features import make_orb_cpu
from slam.types import CameraModel
from slam.vocab import VOCAB_PATH, save_vocabulary, train_vocabulary

SIM_SCENARIOS = ("nominal", "survey", "urban", "orbit", "nadir", "dark", "bright")
SIM_SEEDS = (1, 2)
PHOTOS = ("astronaut", "chelsea", "coffee", "rocket", "hubble_deep_field", "immunohistochemistry", "gravel",
          "retina", "cell", "clock")
W_PX, H_PX = 640, 480


def sim_descriptors(scenarios, seeds, frames_per_flight: int, n_features: int) -> list[np.ndarray]:
    """ORB descriptors of frames spread evenly over each simulated flight."""
    from companion.sim.scenario import make_scenario

    out = []
    for name in scenarios:
        for seed in seeds:
            sc = make_scenario(name, seed=seed)
            extract = make_orb_cpu(sc.camera, n_features)
            for i in np.linspace(0, sc.n_frames - 1, frames_per_flight + 2)[1:-1].astype(int):
                d = extract(sc.render(int(i)).image_bgr).desc
                if len(d):
                    out.append(d)
    return out


def random_view(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The photo through a random homography (any rotation, scale 0.6-1.6, some tilt) onto a
    640x480 canvas."""
    h, w = img.shape
    s = rng.uniform(0.6, 1.6) * min(W_PX / w, H_PX / h) * 1.3
    A = cv2.getRotationMatrix2D((w / 2, h / 2), rng.uniform(-180, 180), s)
    A[:, 2] += [W_PX / 2 - w / 2, H_PX / 2 - h / 2]
    H = np.vstack([A, [rng.normal(0, 2e-4), rng.normal(0, 2e-4), 1.0]])
    return cv2.warpPerspective(img, H, (W_PX, H_PX), borderMode=cv2.BORDER_REFLECT)


def photo_descriptors(names, views: int, n_features: int, seed: int) -> list[np.ndarray]:
    import skimage.data

    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, W_PX / 2], [0, 500.0, H_PX / 2], [0, 0, 1]])
    extract = make_orb_cpu(CameraModel(W_PX, H_PX, K), n_features)
    out = []
    for name in names:
        img = getattr(skimage.data, name)()
        gray = img if img.ndim == 2 else cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
        for _ in range(views):
            d = extract(random_view(gray, rng)).desc
            if len(d):
                out.append(d)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=VOCAB_PATH)
    ap.add_argument("--k", type=int, default=16, help="branching factor")
    ap.add_argument("--levels", type=int, default=4, help="tree depth (k**levels words)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sim-frames", type=int, default=20, help="frames per simulated flight")
    ap.add_argument("--photo-views", type=int, default=16, help="random views per photo")
    ap.add_argument("--features", type=int, default=1000)
    ap.add_argument("--cache", type=Path, help="descriptors gathered once, reused by later runs (npz)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    if a.cache is not None and a.cache.exists():
        with np.load(a.cache) as z:
            images, n_sim = [z[f"i{j}"] for j in range(int(z["n"]))], int(z["n_sim"])
    else:
        sim = sim_descriptors(SIM_SCENARIOS, SIM_SEEDS, a.sim_frames, a.features)
        images, n_sim = sim + photo_descriptors(PHOTOS, a.photo_views, a.features, a.seed), len(sim)
        if a.cache is not None:
            np.savez(a.cache, n=len(images), n_sim=n_sim, **{f"i{j}": d for j, d in enumerate(images)})
    t1 = time.perf_counter()
    meta = dict(command="python -m companion.slam_bench.vocab_train " + " ".join(argv if argv is not None else __import__("sys").argv[1:]),
                sim_scenarios=list(SIM_SCENARIOS), sim_seeds=list(SIM_SEEDS), sim_frames_per_flight=a.sim_frames,
                sim_images=n_sim, photos=list(PHOTOS), photo_views=a.photo_views, features=a.features)
    vocab = train_vocabulary(images, a.k, a.levels, a.seed, meta)
    digest = save_vocabulary(vocab, a.out)
    print(f"{len(images)} images ({n_sim} simulated), {vocab.meta['descriptors']} descriptors gathered in "
          f"{t1 - t0:.0f} s; {vocab.n_words} words ({vocab.meta['words_used']} used) trained in "
          f"{time.perf_counter() - t1:.0f} s -> {a.out} ({a.out.stat().st_size / 1024:.0f} KiB, sha256 {digest})")


if __name__ == "__main__":
    main()
