"""Place recognition without anything downloaded: a bag of binary words (slam/vocab.py).

Each keyframe is stored as its sparse tf-idf word vector over the shipped vocabulary's 65536
words (all its features; ~850 words, 12 B a word) in an inverted file: one array of (word,
weight, keyframe) postings sorted by word. A query quantises its descriptors (~2 ms for 1000),
finds its words' postings by binary search and sums DBoW2's L1 score ``sum_w min(q_w, v_w)`` per
keyframe, in [0, 1]: it touches only the postings of its own words (a word is held by few
keyframes), so hundreds of keyframes cost about as little as ten. Adding merges ~850 postings into
the sorted arrays (a copy of them: about a millisecond at 600 keyframes). Local mapping bounds
the entries: the newest ``slam.max_keyframes`` keyframes plus at most ``slam.max_loop_anchors``
older ones (slam/mapping.py ``_forget_old``).

Figures: ``python -m companion.slam_bench.place_eval bench`` (add/query time against the number of entries) and
``python -m companion.slam_bench.place_eval recall`` (recognition on the simulator's loop revisits).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from slam.vocab import Vocabulary, shipped_vocabulary


@dataclass(frozen=True)
class PlaceCandidate:
    kf_id: int
    score: float  # DBoW2 L1 score of the tf-idf word vectors: 0 no word in common .. 1 identical


@dataclass(frozen=True)
class _Postings:
    """The inverted file: every held keyframe's (word, weight) pairs sorted by word. Replaced, never
    mutated, so a query reads one consistent version outside the lock."""

    words: np.ndarray  # (P,) int32 ascending
    weights: np.ndarray  # (P,) float32
    kf_ids: np.ndarray  # (P,) int32 (keyframe ids are counters; 2**31 keyframes is years of flight)


_EMPTY = _Postings(np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(0, np.int32))


def _ranges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Concatenation of arange(lo[i], hi[i]) for all i, without a Python loop."""
    lengths = hi - lo
    starts = np.repeat(lo - np.r_[0, np.cumsum(lengths)[:-1]], lengths)
    return starts + np.arange(lengths.sum())


class PlaceIndex:
    """Thread-safe: local mapping adds and removes keyframes, loop closing and the tracker's
    relocalisation query (one lock around changes; quantising and scoring run outside it)."""

    def __init__(self, vocabulary: Vocabulary | None = None) -> None:
        self.vocab = vocabulary if vocabulary is not None else shipped_vocabulary()
        self._lock = threading.Lock()
        self._post = _EMPTY
        self._held: set[int] = set()

    def __len__(self) -> int:
        return len(self._held)

    def nbytes(self) -> int:
        p = self._post
        return p.words.nbytes + p.weights.nbytes + p.kf_ids.nbytes

    def add(self, kf_id: int, desc: np.ndarray) -> None:
        """Index a keyframe's descriptors (a keyframe added again replaces its entry)."""
        words, weights = self.vocab.bow(desc)
        with self._lock:
            p = self._without(self._post, [kf_id]) if kf_id in self._held else self._post
            at = np.searchsorted(p.words, words)  # merge: O(P) copies, no re-sort
            self._post = _Postings(np.insert(p.words, at, words), np.insert(p.weights, at, weights),
                                   np.insert(p.kf_ids, at, np.int32(kf_id)))
            self._held.add(kf_id)

    @staticmethod
    def _without(p: _Postings, kf_ids) -> _Postings:
        keep = ~np.isin(p.kf_ids, np.asarray(list(kf_ids), np.int64))
        return _Postings(p.words[keep], p.weights[keep], p.kf_ids[keep])

    def remove(self, kf_ids) -> None:
        """Forget these keyframes (memory cap): their postings are dropped at once."""
        with self._lock:
            gone = self._held.intersection(kf_ids)
            if gone:
                self._post = self._without(self._post, gone)
                self._held -= gone

    def query(self, desc: np.ndarray, exclude_after_kf_id: int | None = None, top: int = 3) -> list[PlaceCandidate]:
        """Keyframes with the highest scores, best first; keyframes with id > exclude_after_kf_id are skipped."""
        q_words, q_weights = self.vocab.bow(desc)
        p = self._post
        lo = np.searchsorted(p.words, q_words, "left")
        hi = np.searchsorted(p.words, q_words, "right")
        hits = _ranges(lo, hi)  # postings of the query's words only
        if len(hits) == 0:
            return []
        contrib = np.minimum(np.repeat(q_weights, hi - lo), p.weights[hits])
        kf_ids, slot = np.unique(p.kf_ids[hits], return_inverse=True)
        score = np.bincount(slot, contrib, minlength=len(kf_ids))
        if exclude_after_kf_id is not None:
            score[kf_ids > exclude_after_kf_id] = 0
        order = np.argsort(-score)[:top]
        return [PlaceCandidate(int(kf_ids[i]), float(score[i])) for i in order if score[i] > 0]


def place_index_of(keyframes) -> PlaceIndex:
    """An index of these keyframes (those that still hold features), e.g. of a map loaded from disk."""
    idx = PlaceIndex()
    for kf in keyframes:
        if kf.has_features:
            idx.add(kf.kf_id, kf.desc)
    return idx
