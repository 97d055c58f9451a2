"""Bag of binary words for place recognition (DBoW2-style), trained by our own code.

A vocabulary is a k-ary tree of ORB descriptor centroids, ``levels`` deep (k**levels leaf words),
built by hierarchical k-majority k-means (k-means in Hamming space: a centroid's bit is the
majority bit of its cluster). An image becomes a sparse tf-idf vector over the leaf words,
L1-normalised; two vectors score ``sum_w min(a_w, b_w)`` = 1 - |a - b|_1 / 2 (DBoW2's L1 score,
0: no word in common, 1: the same words with the same weights).

Hand-written because no kept library provides it: DBoW2/DBoW3/fbow are C++ libraries, the PyPI
packages that wrap or port them (pydbow 0.1.2 of 2022, pydbow3 0.2 of 2019) are single old
releases, and the published ORB vocabularies are downloads of 40-150 MB. Ours is trained by
``python -m companion.slam_bench.vocab_train`` (frames of our simulator + scikit-image photos) and shipped as
``slam/data/orb_vocab.npz`` (package data, 16 x 16 x 16 x 16 = 65536 words, 2.2 MB).
"""
from __future__ import annotations

import functools
import hashlib
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

VOCAB_PATH = Path(__file__).parent / "data" / "orb_vocab.npz"
DESC_BYTES = 32  # ORB: 256-bit descriptors


class VocabularyError(ValueError):
    """A vocabulary file that cannot be read or is inconsistent (the message names the file)."""


@dataclass(frozen=True)
class Vocabulary:
    k: int  # branching factor
    levels: int  # tree depth below the root; leaf words = k**levels
    centroids: np.ndarray  # (sum_{l=1..levels} k**l, 32) uint8, level by level; node i's children: i*k .. i*k+k-1 of the next level
    valid: np.ndarray  # (same,) bool: False for children a node does not have (it held fewer than k descriptors)
    idf: np.ndarray  # (k**levels,) float32, log(training images / training images holding the word)
    meta: dict  # how it was trained (command, data, counts)

    @property
    def n_words(self) -> int:
        return self.k ** self.levels

    def level_start(self, level: int) -> int:
        """Row of the first node of ``level`` (1 = the root's children) in ``centroids``."""
        return sum(self.k ** j for j in range(1, level))

    @functools.cached_property
    def _centroid_columns(self) -> np.ndarray:
        """(4, nodes) uint64: a descriptor as 4 machine words, each column contiguous. Distances
        column by column on (N, k) arrays run ~8x faster than on (N, k, 32) bytes (measured)."""
        return np.ascontiguousarray(self.centroids.view(np.uint64).T)

    def words(self, desc: np.ndarray) -> np.ndarray:
        """Leaf word of each descriptor: descend the tree, nearest valid child (Hamming) per level."""
        cols = np.ascontiguousarray(np.ascontiguousarray(desc, np.uint8).reshape(-1, DESC_BYTES).view(np.uint64).T)
        n = cols.shape[1]
        node = np.zeros(n, np.int64)
        ks = np.arange(self.k)
        for level in range(1, self.levels + 1):
            child = node[:, None] * self.k + ks  # (N, k) node indices within this level
            rows = self.level_start(level) + child
            dist = np.zeros(rows.shape, np.uint16)
            for centroid_col, desc_col in zip(self._centroid_columns, cols):
                dist += np.bitwise_count(centroid_col[rows] ^ desc_col[:, None])
            dist[~self.valid[rows]] = np.iinfo(np.uint16).max
            node = child[np.arange(n), dist.argmin(1)]
        return node

    def bow(self, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sparse tf-idf vector of an image's descriptors: (word ids ascending int32, weights float32
        summing to 1)."""
        if len(desc) == 0:
            return np.zeros(0, np.int32), np.zeros(0, np.float32)
        w, count = np.unique(self.words(desc), return_counts=True)
        weight = count / len(desc) * self.idf[w]
        total = weight.sum()
        if total <= 0:  # every word in every training image: nothing tells places apart
            return np.zeros(0, np.int32), np.zeros(0, np.float32)
        return w.astype(np.int32), (weight / total).astype(np.float32)


def l1_score(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """DBoW2 L1 score of two ``bow`` vectors: sum over common words of the smaller weight."""
    _, ia, ib = np.intersect1d(a[0], b[0], assume_unique=True, return_indices=True)
    return float(np.minimum(a[1][ia], b[1][ib]).sum())


# --- file format ----------------------------------------------------------------------------------

def content_sha256(k: int, levels: int, centroids: np.ndarray, valid: np.ndarray, idf: np.ndarray) -> str:
    h = hashlib.sha256(f"{k},{levels}".encode())
    for a in (centroids, valid, idf):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def save_vocabulary(v: Vocabulary, path: Path) -> str:
    """Write ``v`` (compressed npz with its content hash); returns the hash."""
    digest = content_sha256(v.k, v.levels, v.centroids, v.valid, v.idf)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, k=np.int64(v.k), levels=np.int64(v.levels), centroids=v.centroids, valid=v.valid,
                        idf=v.idf, meta=np.array(json.dumps(v.meta, sort_keys=True)), sha256=np.array(digest))
    return digest


def load_vocabulary(path: Path = VOCAB_PATH) -> Vocabulary:
    """Read and check a vocabulary file; any damage raises VocabularyError naming the file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {name: z[name] for name in ("k", "levels", "centroids", "valid", "idf", "meta", "sha256")}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        raise VocabularyError(f"place-recognition vocabulary {path}: unreadable ({type(e).__name__}: {e}); "
                              f"regenerate it with `python -m companion.slam_bench.vocab_train`") from e
    k, levels = int(arrays["k"]), int(arrays["levels"])
    centroids, valid, idf = arrays["centroids"], arrays["valid"], arrays["idf"]
    n_nodes = sum(k ** j for j in range(1, levels + 1)) if k >= 2 and levels >= 1 else -1
    if (centroids.shape != (n_nodes, DESC_BYTES) or centroids.dtype != np.uint8 or valid.shape != (n_nodes,)
            or valid.dtype != bool or idf.shape != (k ** levels,) or idf.dtype != np.float32):
        raise VocabularyError(f"place-recognition vocabulary {path}: inconsistent shapes (k={k}, levels={levels}, "
                              f"centroids {centroids.shape} {centroids.dtype}, valid {valid.shape}, idf {idf.shape} {idf.dtype})")
    if content_sha256(k, levels, centroids, valid, idf) != str(arrays["sha256"]):
        raise VocabularyError(f"place-recognition vocabulary {path}: content does not match its sha256")
    return Vocabulary(k, levels, centroids, valid, idf, json.loads(str(arrays["meta"])))


@functools.lru_cache(maxsize=1)
def shipped_vocabulary() -> Vocabulary:
    """The vocabulary shipped with the package (read once per process)."""
    return load_vocabulary(VOCAB_PATH)


# --- training -------------------------------------------------------------------------------------

def hamming_to(desc: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """(N, M) Hamming distances, one centre at a time (N x 32 bytes of scratch, not N x M x 32)."""
    out = np.empty((len(desc), len(centers)), np.int32)
    for j, c in enumerate(centers):
        out[:, j] = np.bitwise_count(desc ^ c).sum(1, dtype=np.int32)
    return out


def majority(desc: np.ndarray) -> np.ndarray:
    """Bitwise majority of binary descriptors (ties give 0, as in DBoW2)."""
    bits = np.unpackbits(desc, axis=1)
    return np.packbits(bits.sum(0) * 2 > len(desc))


def k_majority(desc: np.ndarray, k: int, rng: np.random.Generator, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """k-means in Hamming space with k-means++ seeding: (centres (m<=k, 32), assignment (N,))."""
    centers = [desc[rng.integers(len(desc))]]
    d_min = hamming_to(desc, np.array(centers))[:, 0].astype(np.float64)
    while len(centers) < k and d_min.sum() > 0:
        p = d_min ** 2
        centers.append(desc[rng.choice(len(desc), p=p / p.sum())])
        d_min = np.minimum(d_min, hamming_to(desc, centers[-1][None])[:, 0])
    centers = np.array(centers)
    assign = hamming_to(desc, centers).argmin(1)
    for _ in range(iterations):
        centers = np.array([majority(desc[assign == j]) for j in range(len(centers)) if np.any(assign == j)])
        new = hamming_to(desc, centers).argmin(1)
        if np.array_equal(new, assign):
            break
        assign = new
    used = np.unique(assign)  # a centre can end up with no members: drop it
    return centers[used], np.searchsorted(used, assign)


def train_vocabulary(images: list[np.ndarray], k: int = 10, levels: int = 4, seed: int = 0,
                     meta: dict | None = None) -> Vocabulary:
    """Vocabulary from the descriptors of training ``images`` (one (N, 32) array per image; the
    image grouping gives the idf)."""
    rng = np.random.default_rng(seed)
    desc = np.concatenate(images).astype(np.uint8)
    centroids = np.zeros((sum(k ** j for j in range(1, levels + 1)), DESC_BYTES), np.uint8)
    valid = np.zeros(len(centroids), bool)
    members = [np.arange(len(desc))]  # descriptors under each node of the current level
    start = 0
    for level in range(1, levels + 1):
        children: list[np.ndarray] = []
        for node, idx in enumerate(members):
            if len(idx) <= k:  # a leaf-sized set: each descriptor its own child
                centers, assign = desc[idx], np.arange(len(idx))
            else:
                centers, assign = k_majority(desc[idx], k, rng)
            rows = start + node * k + np.arange(len(centers))
            centroids[rows], valid[rows] = centers, True
            children += [idx[assign == j] for j in range(len(centers))] + [idx[:0]] * (k - len(centers))
        members, start = children, start + k ** level
    v = Vocabulary(k, levels, centroids, valid, np.ones(k ** levels, np.float32), dict(meta or {}))
    holding = np.zeros(v.n_words, np.int64)  # training images holding each word
    for d in images:
        holding[np.unique(v.words(d))] += 1
    idf = np.log(len(images) / np.maximum(holding, 1)).astype(np.float32)
    info = dict(v.meta, k=k, levels=levels, seed=seed, images=len(images), descriptors=len(desc),
                words_used=int((holding > 0).sum()))
    return Vocabulary(k, levels, centroids, valid, idf, info)
