"""slam/vocab.py: the shipped vocabulary file, its damage checks, and the training algorithm on
constructed descriptors."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from slam.vocab import (
    VOCAB_PATH,
    Vocabulary,
    VocabularyError,
    content_sha256,
    k_majority,
    l1_score,
    load_vocabulary,
    save_vocabulary,
    shipped_vocabulary,
    train_vocabulary,
)

# sha256 of the shipped vocabulary's content (printed by `python -m companion.slam_bench.vocab_train`): a retrained
# file must be committed together with this line.
SHIPPED_SHA256 = "96e68cf4c0b6215ca4be02d32821fdf7390756953fed7efea5705524a6cc9833"


def noisy_copies(center: np.ndarray, n: int, flips: int, rng: np.random.Generator) -> np.ndarray:
    """n descriptors, each ``center`` with ``flips`` random bits flipped."""
    bits = np.tile(np.unpackbits(center), (n, 1))
    for row in bits:
        row[rng.choice(256, flips, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def test_shipped_vocabulary_loads_with_its_recorded_content():
    v = shipped_vocabulary()
    assert (v.k, v.levels) == (16, 4)
    assert v.centroids.shape == (16 + 256 + 4096 + 65536, 32) and v.idf.shape == (65536,)
    assert content_sha256(v.k, v.levels, v.centroids, v.valid, v.idf) == SHIPPED_SHA256
    assert v.meta["words_used"] > 60000 and v.meta["sim_images"] > 0 and v.meta["descriptors"] > 300_000
    assert VOCAB_PATH.stat().st_size < 3 * 2**20
    assert np.all(v.idf >= 0) and v.idf.max() > 0


def test_damaged_vocabulary_files_are_named_in_the_error(tmp_path):
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(VOCAB_PATH.read_bytes()[:5000])
    with pytest.raises(VocabularyError, match="truncated.npz"):
        load_vocabulary(truncated)
    with pytest.raises(VocabularyError, match="missing.npz"):
        load_vocabulary(tmp_path / "missing.npz")
    v = load_vocabulary(VOCAB_PATH)
    tampered = tmp_path / "tampered.npz"  # valid zip and shapes, one centroid changed after hashing
    shutil.copy(VOCAB_PATH, tampered)
    with np.load(tampered) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["centroids"] = arrays["centroids"].copy()
    arrays["centroids"][5, 0] ^= 1
    np.savez_compressed(tampered, **arrays)
    with pytest.raises(VocabularyError, match="tampered.npz.*sha256"):
        load_vocabulary(tampered)
    arrays["idf"] = arrays["idf"][:-1]
    np.savez_compressed(tampered, **arrays)
    with pytest.raises(VocabularyError, match="tampered.npz.*shapes"):
        load_vocabulary(tampered)
    assert load_vocabulary(VOCAB_PATH).k == v.k  # the real file is untouched


def test_k_majority_recovers_separated_binary_clusters():
    rng = np.random.default_rng(0)
    centers = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    desc = np.concatenate([noisy_copies(c, 50, 20, rng) for c in centers])
    found, assign = k_majority(desc, 4, np.random.default_rng(1))
    assert len(found) == 4
    for j in range(4):  # each true cluster lands in one found cluster, whose centre is the true one
        labels = assign[j * 50:(j + 1) * 50]
        assert len(set(labels.tolist())) == 1
        assert np.array_equal(found[labels[0]], centers[j])


def test_trained_words_separate_places_and_score_by_l1(tmp_path):
    rng = np.random.default_rng(2)
    centers = rng.integers(0, 256, (60, 32), dtype=np.uint8)
    # 12 training "images", each a distinct set of 5 textures seen with noise
    images = [np.concatenate([noisy_copies(centers[c], 8, 10, rng) for c in range(5 * i, 5 * i + 5)])
              for i in range(12)]
    v = train_vocabulary(images, k=4, levels=3, seed=0)
    path = tmp_path / "v.npz"
    save_vocabulary(v, path)
    v2 = load_vocabulary(path)
    assert isinstance(v2, Vocabulary) and np.array_equal(v2.centroids, v.centroids) and v2.meta["images"] == 12
    a, a_again, b = v.bow(images[3]), v.bow(np.concatenate([noisy_copies(centers[c], 8, 10, rng)
                                                            for c in range(15, 20)])), v.bow(images[7])
    assert a[1].sum() == pytest.approx(1.0) and l1_score(a, a) == pytest.approx(1.0)
    assert l1_score(a, a_again) > 0.5 > 0.05 > l1_score(a, b)


def test_inverted_file_scores_equal_pairwise_l1_scores():
    from slam.place import PlaceIndex

    rng = np.random.default_rng(4)
    base = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    # keyframes sharing parts of one scene (overlapping slices) plus unrelated ones
    descs = [base[40 * i:40 * i + 160] for i in range(6)] + [rng.integers(0, 256, (160, 32), dtype=np.uint8)
                                                           for _ in range(4)]
    idx = PlaceIndex()
    for k, d in enumerate(descs):
        idx.add(100 + k, d)
    idx.remove([103])
    v = idx.vocab
    query = base[100:260]
    got = {c.kf_id: c.score for c in idx.query(query, top=20)}
    want = {100 + k: l1_score(v.bow(query), v.bow(d)) for k, d in enumerate(descs) if k != 3}
    want = {k: s for k, s in want.items() if s > 0}
    assert got.keys() == want.keys() and all(got[k] == pytest.approx(want[k], abs=1e-6) for k in want)
    # ranked by overlap with the query (slice 100:260): 102 (140 of 160), 101 and 104 (100), 100 and 105 (60)
    assert max(got, key=got.get) == 102 and got[102] > got[101] > got[100] and got[104] > got[105]
    assert max(got.get(k, 0.0) for k in range(106, 110)) < 0.05  # unrelated keyframes


def test_place_index_queries_while_another_thread_adds_and_removes():
    import threading

    from slam.place import PlaceIndex

    rng = np.random.default_rng(6)
    descs = [rng.integers(0, 256, (200, 32), dtype=np.uint8) for _ in range(60)]
    idx, errors, done = PlaceIndex(), [], threading.Event()

    def mapper():
        try:
            for k, d in enumerate(descs):
                idx.add(k, d)
                if k >= 10:
                    idx.remove([k - 10])  # a sliding window of 10 held keyframes
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)
        finally:
            done.set()

    t = threading.Thread(target=mapper)
    t.start()
    seen = 0
    while not done.is_set():
        for c in idx.query(descs[min(seen, 59)], top=3):
            assert 0 < c.score <= 1 + 1e-6 and 0 <= c.kf_id < 60
        seen += 1
    t.join()
    assert not errors and len(idx) == 10
    assert idx.query(descs[59])[0].kf_id == 59 and all(c.kf_id >= 50 for c in idx.query(descs[20], top=10))
