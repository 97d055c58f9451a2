"""Place recognition without anything downloaded: an incremental binary-descriptor index.

Each keyframe contributes a spread subset (400) of its ORB descriptors to an OpenCV brute-force Hamming
matcher (compiled, appended incrementally with ``add``); a query (all its descriptors) votes with its ratio-test-passing
nearest neighbours for the keyframes they came from. No vocabulary to train or ship; cost grows
linearly with the number of keyframes held, which local mapping bounds: the newest
``slam.max_keyframes`` keyframes plus at most ``slam.max_loop_anchors`` older ones (slam/mapping.py
``_forget_old``), 400 × 32 B = 12.8 KB of descriptors each.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class PlaceCandidate:
    kf_id: int
    votes: int


class PlaceIndex:
    """Thread-safe: local mapping adds and removes keyframes, loop closing and the tracker's
    relocalisation query (one lock; OpenCV's matcher is not safe to use from two threads)."""

    def __init__(self, per_keyframe: int = 400, ratio: float = 0.8, max_dist: int = 64) -> None:
        self._lock = threading.Lock()
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._kf_ids: list[int] = []  # train-set order of the matcher (may still hold removed ones)
        self._stored: dict[int, np.ndarray] = {}  # the live entries
        self.per_keyframe = per_keyframe
        self.ratio = ratio
        self.max_dist = max_dist

    def __len__(self) -> int:
        return len(self._stored)

    def nbytes(self) -> int:
        with self._lock:
            return sum(d.nbytes for d in self._stored.values())

    def _subset(self, desc: np.ndarray) -> np.ndarray:
        if len(desc) <= self.per_keyframe:
            return desc
        return desc[np.linspace(0, len(desc) - 1, self.per_keyframe).astype(int)]

    def add(self, kf_id: int, desc: np.ndarray) -> None:
        sub = np.ascontiguousarray(self._subset(desc))
        with self._lock:
            self._matcher.add([sub])
            self._kf_ids.append(kf_id)
            self._stored[kf_id] = sub

    def remove(self, kf_ids) -> None:
        """Forget these keyframes (memory cap). Queries ignore them at once; the matcher's train set
        is rebuilt once removed entries exceed 10 % of the live ones (amortised)."""
        with self._lock:
            for k in kf_ids:
                self._stored.pop(k, None)
            if len(self._kf_ids) - len(self._stored) > 0.1 * len(self._stored):
                self._matcher.clear()
                self._kf_ids = [k for k in self._kf_ids if k in self._stored]
                if self._kf_ids:
                    self._matcher.add([self._stored[k] for k in self._kf_ids])

    def query(self, desc: np.ndarray, exclude_after_kf_id: int | None = None, top: int = 3) -> list[PlaceCandidate]:
        """Keyframes with the most votes, best first; keyframes with id > exclude_after_kf_id are skipped."""
        if len(desc) < 2:
            return []
        with self._lock:
            if len(self._stored) == 0:
                return []
            knn = self._matcher.knnMatch(np.ascontiguousarray(desc), k=2)
            ids = np.array(self._kf_ids)
            live = np.array([k in self._stored for k in self._kf_ids])
        votes = np.zeros(len(ids), int)
        for pair in knn:
            if len(pair) == 2 and pair[0].distance < self.max_dist and pair[0].distance < self.ratio * pair[1].distance:
                votes[pair[0].imgIdx] += 1
        votes[~live] = 0
        if exclude_after_kf_id is not None:
            votes[ids > exclude_after_kf_id] = 0
        order = np.argsort(-votes)[:top]
        return [PlaceCandidate(int(ids[i]), int(votes[i])) for i in order if votes[i] > 0]


def place_index_of(keyframes) -> PlaceIndex:
    """An index of these keyframes (those that still hold features), e.g. of a map loaded from disk."""
    idx = PlaceIndex()
    for kf in keyframes:
        if kf.has_features:
            idx.add(kf.kf_id, kf.desc)
    return idx
