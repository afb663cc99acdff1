"""Keyframe database: an inverted index word -> keyframes (ORB-SLAM2 ``KeyFrameDatabase``).

Every keyframe is added with its :class:`~dynastereo.slam.vocabulary.BowVector`; a query
gathers the postings of the query's words, counts the words each keyframe shares with
the query and computes DBoW2's L1 score for all of them at once (``np.bincount``; the L1
score of two L1-normalized vectors is the sum over common words of ``min(q_w, v_w)``).

The index is a CSR by word (``indptr`` into postings of (keyframe slot, weight)) plus a
small append-only *delta* of recent additions, merged into the CSR when it grows past
``merge_postings`` entries (amortized: adding a keyframe costs O(its words), a merge
O(all postings)).  Erasing marks the keyframe's slot dead; dead postings are dropped at
the next merge.  No Python loop over postings or words; the loops in
:meth:`detect_loop_candidates` run over the few candidate keyframes and their 10 best
covisibles, as ORB-SLAM2's do.
"""

from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

from .vocabulary import BowVector, Vocabulary


class KeyFrameDatabase:
    """Inverted index of keyframe bag-of-words vectors (see the module docstring)."""

    def __init__(self, vocab: Vocabulary, merge_postings: int = 65536) -> None:
        self.vocab = vocab
        self.merge_postings = int(merge_postings)
        self._bows: dict[int, BowVector] = {}
        self._slot: dict[int, int] = {}  # keyframe id -> slot
        self._ids = np.zeros(0, np.int64)  # slot -> keyframe id
        self._alive = np.zeros(0, bool)
        self._n_slots = 0
        # CSR part: postings sorted by word
        self._indptr = np.zeros(vocab.n_words + 1, np.int64)
        self._p_slot = np.zeros(0, np.int64)
        self._p_w = np.zeros(0, np.float64)
        # delta part: appended chunks (words, slot, weights), concatenated lazily
        self._d_chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._d_cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._d_n = 0
        self._dead_postings = 0

    # ------------------------------------------------------------------ contents
    def __len__(self) -> int:
        return len(self._bows)

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self._bows

    def ids(self) -> list[int]:
        """Keyframe ids in the database (insertion order)."""
        return list(self._bows)

    def bow(self, kf_id: int) -> BowVector:
        """The BowVector a keyframe was added with (KeyError if absent)."""
        return self._bows[kf_id]

    @property
    def n_postings(self) -> int:
        return len(self._p_slot) + self._d_n - self._dead_postings

    def add(self, kf_id: int, bow: BowVector) -> None:
        """Add (or replace) a keyframe's bag of words."""
        kf_id = int(kf_id)
        if kf_id in self._bows:
            self.erase(kf_id)
        words = np.asarray(bow.words, np.int64)
        if len(words) and (words[0] < 0 or words[-1] >= self.vocab.n_words):
            raise ValueError(f"keyframe {kf_id}: word ids outside this vocabulary's 0..{self.vocab.n_words - 1}")
        slot = self._n_slots
        if slot >= len(self._ids):
            cap = max(64, 2 * len(self._ids))
            self._ids = np.resize(self._ids, cap)
            self._alive = np.concatenate([self._alive, np.zeros(cap - len(self._alive), bool)])
        self._ids[slot] = kf_id
        self._alive[slot] = True
        self._n_slots += 1
        self._slot[kf_id] = slot
        self._bows[kf_id] = bow
        if len(words):
            self._d_chunks.append((words, np.full(len(words), slot, np.int64), np.asarray(bow.weights, np.float64)))
            self._d_n += len(words)
            self._d_cache = None
        if self._d_n > self.merge_postings:
            self._merge()

    def erase(self, kf_id: int) -> None:
        """Remove a keyframe (no-op if absent)."""
        kf_id = int(kf_id)
        if kf_id not in self._bows:
            return
        slot = self._slot.pop(kf_id)
        self._alive[slot] = False
        self._dead_postings += len(self._bows.pop(kf_id))
        if self._dead_postings > max(self.merge_postings, len(self._p_slot) // 2):
            self._merge()

    def clear(self) -> None:
        self.__init__(self.vocab, self.merge_postings)  # type: ignore[misc]

    def _delta(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._d_cache is None:
            if self._d_chunks:
                self._d_cache = tuple(np.concatenate(a) for a in zip(*self._d_chunks))  # type: ignore[assignment]
                self._d_chunks = [self._d_cache]  # type: ignore[list-item]
            else:
                z = np.zeros(0, np.int64)
                self._d_cache = (z, z, np.zeros(0, np.float64))
        return self._d_cache  # type: ignore[return-value]

    def _merge(self) -> None:
        """Fold the delta into the CSR and drop the postings of erased keyframes."""
        dw, ds, dv = self._delta()
        nw = self.vocab.n_words
        cw = np.repeat(np.arange(nw, dtype=np.int64), np.diff(self._indptr))
        w = np.concatenate([cw, dw])
        s = np.concatenate([self._p_slot, ds])
        v = np.concatenate([self._p_w, dv])
        keep = self._alive[s]
        w, s, v = w[keep], s[keep], v[keep]
        o = np.argsort(w, kind="stable")  # stable: postings of a word stay in slot order
        self._p_slot, self._p_w = s[o], v[o]
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(w, minlength=nw))]).astype(np.int64)
        self._d_chunks, self._d_cache, self._d_n, self._dead_postings = [], None, 0, 0

    # ------------------------------------------------------------------ scoring
    def _shared(self, bow: BowVector) -> tuple[np.ndarray, np.ndarray]:
        """Per slot: number of words shared with ``bow`` and the L1 score (dead slots 0)."""
        n = self._n_slots
        common = np.zeros(n, np.int64)
        score = np.zeros(n, np.float64)
        if len(bow) == 0 or n == 0:
            return common, score
        qw = np.asarray(bow.words, np.int64)
        qv = np.asarray(bow.weights, np.float64)
        # CSR postings of the query's words
        lo = self._indptr[qw]
        cnt = self._indptr[qw + 1] - lo
        total = int(cnt.sum())
        pos = np.repeat(lo - np.cumsum(cnt) + cnt, cnt) + np.arange(total)
        slots = np.take(self._p_slot, pos)  # np.take: faster than fancy indexing here
        m = np.minimum(np.take(self._p_w, pos), np.repeat(qv, cnt))
        # delta postings whose word is in the query
        dw, ds, dv = self._delta()
        if len(dw):
            j = np.searchsorted(qw, dw)
            j[j == len(qw)] = 0
            hit = qw[j] == dw
            slots = np.concatenate([slots, ds[hit]])
            m = np.concatenate([m, np.minimum(dv[hit], qv[j[hit]])])
        common += np.bincount(slots, minlength=n)[:n]
        score += np.bincount(slots, weights=m, minlength=n)[:n]
        dead = ~self._alive[:n]
        common[dead] = 0
        score[dead] = 0.0
        np.clip(score, 0.0, 1.0, out=score)
        return common, score

    def scores(self, bow: BowVector, kf_ids: Iterable[int] | None = None) -> np.ndarray | dict[int, float]:
        """L1 scores of ``bow`` against keyframes: an array in ``kf_ids`` order (0 for ids
        not in the database), or ``{id: score}`` over all keyframes when ``kf_ids`` is None."""
        _, score = self._shared(bow)
        if kf_ids is None:
            return {kid: float(score[s]) for kid, s in self._slot.items()}
        ids = list(kf_ids)
        slots = np.array([self._slot.get(int(i), -1) for i in ids], np.int64)
        out = np.zeros(len(ids))
        ok = slots >= 0
        out[ok] = score[slots[ok]]
        return out

    def query(self, bow: BowVector, exclude: Iterable[int] = (), top: int = 10) -> list[tuple[int, float]]:
        """The ``top`` keyframes by L1 score with ``bow`` (sharing at least one word, not in
        ``exclude``): ``[(kf_id, score)]``, best first, ties by smaller id."""
        common, score = self._shared(bow)
        excl = [self._slot[i] for i in exclude if i in self._slot]
        if excl:
            common[excl] = 0
        cand = np.flatnonzero(common > 0)
        if len(cand) == 0:
            return []
        ids = self._ids[cand]
        o = np.lexsort((ids, -score[cand]))[: max(0, int(top))]
        return [(int(ids[i]), float(score[cand[i]])) for i in o]

    def _candidates(
        self,
        bow: BowVector,
        exclude: Iterable[int],
        min_score: float,
        covisibles: Callable[[int], list[int]],
        n_covisibles: int,
    ) -> list[tuple[int, float]]:
        """ORB-SLAM2's DetectLoopCandidates / DetectRelocalizationCandidates core."""
        common, score = self._shared(bow)
        excl = [self._slot[i] for i in exclude if i in self._slot]
        if excl:
            common[excl] = 0
        if not common.any():
            return []
        min_common = 0.8 * common.max()
        scored = common > min_common  # the keyframes ORB-SLAM2 computes a score for
        matched = np.flatnonzero(scored & (score >= min_score))
        if len(matched) == 0:
            return []
        acc_list: list[tuple[float, int]] = []
        for s in matched[np.argsort(-score[matched], kind="stable")]:  # a few dozen keyframes
            kid = int(self._ids[s])
            best_score, best_id, acc = float(score[s]), kid, float(score[s])
            for nb in list(covisibles(kid))[:n_covisibles]:
                ns = self._slot.get(int(nb), -1)
                if ns < 0 or not scored[ns]:
                    continue
                acc += float(score[ns])
                if score[ns] > best_score or (score[ns] == best_score and int(nb) < best_id):  # ties: smaller id
                    best_score, best_id = float(score[ns]), int(nb)
            acc_list.append((acc, best_id))
        best_acc = max(a for a, _ in acc_list)
        out: dict[int, float] = {}
        for acc, kid in sorted(acc_list, key=lambda t: (-t[0], t[1])):
            if acc > 0.75 * best_acc and kid not in out:
                out[kid] = acc
        return list(out.items())

    def detect_loop_candidates(
        self,
        kf_id: int,
        bow: BowVector,
        connected: set[int],
        min_score: float,
        covisibles: Callable[[int], list[int]],
        n_covisibles: int = 10,
    ) -> list[int]:
        """Loop candidates of keyframe ``kf_id`` (ORB-SLAM2 ``DetectLoopCandidates``).

        Keyframes sharing words with ``bow``, not ``kf_id`` and not in ``connected`` (its
        covisible keyframes); of those, the ones sharing more than 0.8 x the largest
        number of common words and scoring >= ``min_score``; each such keyframe's score is
        accumulated over its ``n_covisibles`` best covisibles (``covisibles(id)``, best
        first) that passed the common-words test, and the best-scoring keyframe of each
        group is kept; returned are those with accumulated score > 0.75 x the best
        accumulated score, best first (ids unique).
        """
        exclude = set(int(c) for c in connected)
        exclude.add(int(kf_id))
        return [k for k, _ in self._candidates(bow, exclude, float(min_score), covisibles, n_covisibles)]

    def detect_relocalization_candidates(
        self, bow: BowVector, covisibles: Callable[[int], list[int]], n_covisibles: int = 10
    ) -> list[int]:
        """Relocalization candidates of a frame (ORB-SLAM2 ``DetectRelocalizationCandidates``):
        as :meth:`detect_loop_candidates` without excluded keyframes and minimum score."""
        return [k for k, _ in self._candidates(bow, (), -np.inf, covisibles, n_covisibles)]

    def detect_candidates_scored(
        self,
        bow: BowVector,
        covisibles: Callable[[int], list[int]],
        exclude: Iterable[int] = (),
        min_score: float = -np.inf,
        n_covisibles: int = 10,
    ) -> list[tuple[int, float]]:
        """The candidates of the two detectors with their accumulated scores, best first."""
        return self._candidates(bow, set(int(e) for e in exclude), float(min_score), covisibles, n_covisibles)

    # ------------------------------------------------------------------ persistence
    def export(self) -> dict[str, np.ndarray]:
        """The database as flat arrays (for a saved map): keyframe ids, CSR of their
        BowVectors, and the vocabulary fingerprint (checked by :meth:`from_export`)."""
        ids = list(self._bows)
        bows = [self._bows[i] for i in ids]
        lens = np.array([len(b) for b in bows], np.int64)
        return {
            "kf_ids": np.array(ids, np.int64),
            "bow_indptr": np.concatenate([[0], np.cumsum(lens)]).astype(np.int64),
            "bow_words": np.concatenate([b.words for b in bows]).astype(np.int64) if bows else np.zeros(0, np.int64),
            "bow_weights": np.concatenate([b.weights for b in bows]).astype(np.float64) if bows else np.zeros(0),
            "vocab_fingerprint": np.array(self.vocab.fingerprint),
        }

    @classmethod
    def from_export(cls, vocab: Vocabulary, arrays: dict[str, np.ndarray]) -> "KeyFrameDatabase":
        """Rebuild from :meth:`export`; ValueError if it was made with another vocabulary."""
        fp = str(np.asarray(arrays["vocab_fingerprint"])[()])
        if fp != vocab.fingerprint:
            raise ValueError("keyframe database was built with another vocabulary (fingerprint differs)")
        db = cls(vocab)
        ptr = np.asarray(arrays["bow_indptr"], np.int64)
        w = np.asarray(arrays["bow_words"], np.int64)
        v = np.asarray(arrays["bow_weights"], np.float64)
        for i, kid in enumerate(np.asarray(arrays["kf_ids"], np.int64)):
            db.add(int(kid), BowVector(w[ptr[i] : ptr[i + 1]].copy(), v[ptr[i] : ptr[i + 1]].copy()))
        db._merge()
        return db
