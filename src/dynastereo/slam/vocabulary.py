"""Bag of binary words for ORB descriptors: a vocabulary tree in numpy (DBoW2-style).

The vocabulary is a ``k``-ary tree of ``levels`` levels below the root, learnt by
hierarchical binary k-medians (k-means++ seeding, Hamming distances, majority-bit
centres) as in DBoW2.  Its leaves are the *words*.  A set of descriptors becomes a
:class:`BowVector` (sparse tf-idf weights, L1-normalized) and, per descriptor, the id of
its node at a coarser level (ORB-SLAM2's ``FeatureVector``: matching restricted to
descriptors under the same node).

Layout: nodes are held as *dense slots* per level -- level ``l`` (root = level 0) has
``k**l`` slots, and the children of slot ``p`` are the slots ``p*k .. p*k + k-1`` of level
``l+1``; slots without a node are marked invalid.  A node that is not split further
(a cluster of one descriptor) is carried down as its own only child, so every path from
the root ends at the last level; the words are the valid slots of the last level, in
slot order.  Descending the tree for ``N`` descriptors is ``levels`` array operations on
``(N, k, 4)`` uint64 arrays (``np.bitwise_count``): no Python loop over descriptors.

File format (``save`` / ``load``): a NumPy ``.npz`` archive (no pickled objects) with

==================  ============================================================
``format``          the string ``"dynastereo-orb-vocabulary"``
``version``         format version, ``1``
``k``, ``levels``   branching factor and depth
``nodes_<l>``       (l = 1..levels) sorted int64 slot ids of the valid nodes of level l
``centres_<l>``     their centres, (M_l, 32) uint8 ORB descriptors
``idf``             (n_words,) float64 inverse document frequency per word (words =
                    ``nodes_<levels>`` in order); all ones when trained without images
``meta``            JSON string: what it was trained on (images, descriptors, seed, ...)
==================  ============================================================

A missing, corrupt, truncated, wrong-format or wrong-version file raises
:class:`~dynastereo.errors.VocabularyError` (an :class:`~dynastereo.errors.InputError`) naming the file.

:meth:`Vocabulary.default` loads the vocabulary shipped with the package
(``slam/data/orb_vocab_synth.npz``), trained on images of dynastereo's own synthetic
generator (licence-clean and reproducible: ``benchmarks/bench_vocab.py --train-default``).
"""

from __future__ import annotations

import glob
import hashlib
import json
import zipfile
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..config import SlamConfig
from ..errors import InputError, VocabularyError
from ..io.outputs import atomic_open
from ..io.images import IMAGE_SUFFIXES, list_images, read_image
from .orb import ORBExtractor

FORMAT_NAME = "dynastereo-orb-vocabulary"
FORMAT_VERSION = 1
DEFAULT_VOCABULARY = "orb_vocab_synth.npz"
_BIG = np.int32(1 << 20)  # distance of an invalid child: never the nearest
_MAX_SLOTS = 1 << 24  # k**levels limit of the dense layout (16.7M leaf slots)


@dataclass(frozen=True, eq=False)
class BowVector:
    """Sparse bag-of-words vector: unique ``words`` ascending, L1-normalized ``weights``.

    An empty vector (no descriptors, or only zero-weight words) is allowed.
    """

    words: np.ndarray  # (n,) int64, sorted ascending, unique
    weights: np.ndarray  # (n,) float64 > 0, sum 1 (or n = 0)

    def __len__(self) -> int:
        return len(self.words)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, BowVector):
            return NotImplemented
        return np.array_equal(self.words, other.words) and np.array_equal(self.weights, other.weights)

    __hash__ = None  # type: ignore[assignment]

    @classmethod
    def empty(cls) -> "BowVector":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.float64))


def _as_u64(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 descriptors (or (N, 4) uint64) -> contiguous (N, 4) uint64."""
    d = np.asarray(desc)
    if d.dtype == np.uint64 and d.ndim == 2 and d.shape[1] == 4:
        return np.ascontiguousarray(d)
    if d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != 32:
        if d.size == 0:
            return np.zeros((0, 4), np.uint64)
        raise ValueError(f"ORB descriptors must be (N, 32) uint8, got {d.shape} {d.dtype}")
    return np.ascontiguousarray(d).view(np.uint64)


def _hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance of two (N, 4) uint64 arrays."""
    return _popsum(np.bitwise_count(a ^ b))


def _popsum(c: np.ndarray) -> np.ndarray:
    """Sum over the last axis (4 words) of uint8 bit counts, as int32 (explicit adds:
    several times faster than ``sum(axis=-1, dtype=...)`` on such a short axis)."""
    out = c[..., 0].astype(np.int32)
    out += c[..., 1]
    out += c[..., 2]
    out += c[..., 3]
    return out


class Vocabulary:
    """A vocabulary tree of ORB words (see the module docstring for the layout)."""

    def __init__(
        self,
        k: int,
        levels: int,
        centres: Sequence[np.ndarray],
        valid: Sequence[np.ndarray],
        idf: np.ndarray | None = None,
        meta: dict | None = None,
    ) -> None:
        """Low-level constructor: dense per-level ``centres[l-1]`` ((k**l, 4) uint64) and
        ``valid[l-1]`` ((k**l,) bool) for l = 1..levels.  Use :meth:`train` / :meth:`load`."""
        self.k = int(k)
        self.levels = int(levels)
        if self.k < 2 or self.levels < 1 or self.k**self.levels > _MAX_SLOTS:
            raise ValueError(f"vocabulary: need k >= 2, levels >= 1 and k**levels <= {_MAX_SLOTS}, got k={k} levels={levels}")
        if len(centres) != self.levels or len(valid) != self.levels:
            raise ValueError("vocabulary: one centre array per level expected")
        self._centres = tuple(np.ascontiguousarray(c, np.uint64).reshape(-1, self.k, 4) for c in centres)
        self._valid = [np.asarray(v, bool).reshape(-1, self.k) for v in valid]
        for lvl, (c, v) in enumerate(zip(self._centres, self._valid), start=1):
            if c.shape[0] * self.k != self.k**lvl or v.shape != c.shape[:2]:
                raise ValueError(f"vocabulary: level {lvl} arrays have the wrong size")
        # distance penalty of invalid children, per level (added to the Hamming distance)
        self._penalty = tuple(np.where(v, 0, _BIG).astype(np.int32) for v in self._valid)  # tuples: the descent kernel's
        leaf_valid = self._valid[-1].reshape(-1)
        self.leaf_slots = np.flatnonzero(leaf_valid).astype(np.int64)
        self.n_words = int(len(self.leaf_slots))
        self._word_of_slot = np.full(len(leaf_valid), -1, np.int64)
        self._word_of_slot[self.leaf_slots] = np.arange(self.n_words)
        if idf is None:
            idf = np.ones(self.n_words)
        idf = np.asarray(idf, np.float64)
        if idf.shape != (self.n_words,):
            raise ValueError(f"vocabulary: idf has {idf.shape} entries for {self.n_words} words")
        self.idf = idf
        self.meta = dict(meta or {})

    # ------------------------------------------------------------------ properties
    def __repr__(self) -> str:
        return f"Vocabulary(k={self.k}, levels={self.levels}, n_words={self.n_words})"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Vocabulary):
            return NotImplemented
        return (
            self.k == other.k
            and self.levels == other.levels
            and all(np.array_equal(a, b) for a, b in zip(self._valid, other._valid))
            and all(np.array_equal(a[v], b[v]) for a, b, v in zip(self._centres, other._centres, self._valid))
            and np.array_equal(self.idf, other.idf)
        )

    __hash__ = None  # type: ignore[assignment]

    @property
    def fingerprint(self) -> str:
        """sha1 of the tree and weights: a map's stored bag-of-words vectors are only
        valid with the vocabulary of the same fingerprint."""
        h = hashlib.sha1()
        h.update(np.array([self.k, self.levels], np.int64).tobytes())
        for c, v in zip(self._centres, self._valid):
            h.update(np.flatnonzero(v.reshape(-1)).astype(np.int64).tobytes())
            h.update(c.reshape(-1, 4)[v.reshape(-1)].tobytes())
        h.update(self.idf.tobytes())
        return h.hexdigest()

    def node_count(self, level: int) -> int:
        """Number of nodes at ``level`` (root = 0)."""
        return 1 if level == 0 else int(self._valid[level - 1].sum())

    def word_centres(self) -> np.ndarray:
        """(n_words, 32) uint8 descriptors of the words."""
        return self._centres[-1].reshape(-1, 4)[self.leaf_slots].view(np.uint8).reshape(-1, 32)

    # ------------------------------------------------------------------ lookup
    def _descend(self, d64: np.ndarray, record_level: int | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Leaf slot per descriptor (and the slot at ``record_level``): one compiled call
        (:func:`.kernels.hamming.descend_tree`)."""
        from .kernels.hamming import descend_tree

        inside = record_level is not None and 1 <= record_level <= self.levels
        leaf, rec = descend_tree(np.ascontiguousarray(d64, np.uint64), self._centres, self._penalty, self.k,
                                 int(record_level) if inside else -1)
        if record_level == 0:
            return leaf, np.zeros(len(d64), np.int64)
        return leaf, (rec if inside else None)

    def words_of(self, desc: np.ndarray) -> np.ndarray:
        """Word id (leaf) of every descriptor: (N,) int64."""
        d64 = _as_u64(desc)
        if len(d64) == 0:
            return np.zeros(0, np.int64)
        leaf, _ = self._descend(d64)
        return self._word_of_slot[leaf]

    def bow_from_words(self, words: np.ndarray) -> BowVector:
        """tf-idf BowVector of a multiset of word ids (DBoW2 TF_IDF, L1-normalized)."""
        words = np.asarray(words, np.int64)
        if len(words) == 0:
            return BowVector.empty()
        v = np.bincount(words, weights=self.idf[words], minlength=self.n_words)
        nz = np.flatnonzero(v > 0)
        w = v[nz]
        s = w.sum()
        if s <= 0:
            return BowVector.empty()
        return BowVector(nz.astype(np.int64), w / s)

    def transform(self, desc: np.ndarray, node_level: int = 2) -> tuple[BowVector, np.ndarray]:
        """BowVector of a descriptor set and, per descriptor, its node at ``node_level``
        (counted from the root: 1 = the root's children; clipped to ``0..levels``).

        The node ids (ORB-SLAM2's ``FeatureVector`` with levelsup = levels - node_level)
        are dense slot ids of that level: two descriptors may match only if their node
        ids are equal (see :func:`same_node_pairs`).  ORB-SLAM2 uses the level two below
        the root (100 nodes for k = 10), the default here.
        """
        d64 = _as_u64(desc)
        lvl = int(np.clip(node_level, 0, self.levels))
        if len(d64) == 0:
            return BowVector.empty(), np.zeros(0, np.int64)
        leaf, nodes = self._descend(d64, lvl)
        return self.bow_from_words(self._word_of_slot[leaf]), nodes  # type: ignore[return-value]

    @staticmethod
    def score(a: BowVector, b: BowVector) -> float:
        """DBoW2's L1 score ``1 - 0.5 * |a - b|_1`` of two L1-normalized vectors, in [0, 1]
        (= sum over common words of ``min(a_w, b_w)``)."""
        if len(a) == 0 or len(b) == 0:
            return 0.0
        _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
        s = float(np.minimum(a.weights[ia], b.weights[ib]).sum())
        return min(1.0, max(0.0, s))

    # ------------------------------------------------------------------ idf
    def with_idf(self, images: Sequence[np.ndarray]) -> "Vocabulary":
        """A copy whose idf weights are ``log(N / N_w)`` over these per-image descriptor
        sets (``N_w`` = images containing word w; words in no image get ``log N``)."""
        words = [self.words_of(d) for d in images]
        return Vocabulary(self.k, self.levels, self._centres, self._valid, _idf_from_words(words, self.n_words), {**self.meta, "idf_images": len(words)})

    # ------------------------------------------------------------------ training
    @classmethod
    def train(
        cls,
        descriptors: np.ndarray | Sequence[np.ndarray],
        k: int = 10,
        levels: int = 4,
        seed: int = 0,
        progress: Callable[[int, int], None] | None = None,
        images: Sequence[np.ndarray] | None = None,
        max_iter: int = 10,
        meta: dict | None = None,
    ) -> "Vocabulary":
        """Learn a vocabulary by hierarchical binary k-medians (DBoW2's HKmeans).

        ``descriptors``: one (N, 32) uint8 array, or a list of per-image arrays (then the
        idf weights come from those images).  ``images``: per-image descriptor sets for
        the idf weights when ``descriptors`` is one array (default: idf = 1, i.e. tf only;
        see :meth:`with_idf`).  At every level all clusters are split at once (vectorized
        over clusters and descriptors): k-means++ seeding with probability ~ distance^2,
        then up to ``max_iter`` rounds of nearest-centre assignment and majority-bit
        centres (DBoW2's ``meanValue``: a bit is set when at least half the members have
        it).  A cluster of at most ``k`` descriptors gets one child per distinct
        descriptor; a single descriptor is a leaf.  ``progress(level, levels)`` after
        each level.  Deterministic for a seed.
        """
        per_image: list[np.ndarray] | None = None
        if isinstance(descriptors, np.ndarray):
            D = _as_u64(descriptors)
        else:
            per_image = [_as_u64(d) for d in descriptors]
            D = np.concatenate(per_image) if per_image else np.zeros((0, 4), np.uint64)
        if len(D) == 0:
            raise ValueError("vocabulary training needs at least one descriptor")
        k, levels = int(k), int(levels)
        if k < 2 or levels < 1 or k**levels > _MAX_SLOTS:
            raise ValueError(f"vocabulary: need k >= 2, levels >= 1 and k**levels <= {_MAX_SLOTS}, got k={k} levels={levels}")
        rng = np.random.default_rng(seed)
        n = len(D)
        slot = np.zeros(n, np.int64)  # node of every descriptor at the current level
        centres: list[np.ndarray] = []
        valid: list[np.ndarray] = []
        for lvl in range(1, levels + 1):
            child, C, V = _split_level(D, slot, k, rng, max_iter)
            groups = np.unique(slot)
            dense_c = np.zeros((k ** (lvl - 1), k, 4), np.uint64)
            dense_v = np.zeros((k ** (lvl - 1), k), bool)
            dense_c[groups] = C
            dense_v[groups] = V
            centres.append(dense_c)
            valid.append(dense_v)
            slot = slot * k + child
            if progress is not None:
                progress(lvl, levels)
        info = {"descriptors": int(n), "k": k, "levels": levels, "seed": int(seed), "max_iter": int(max_iter)}
        info.update(meta or {})
        vocab = cls(k, levels, centres, valid, None, info)
        leaf_words = vocab._word_of_slot[slot]
        if per_image is not None:
            sizes = np.array([len(d) for d in per_image])
            vocab.idf = _idf_from_words(np.split(leaf_words, np.cumsum(sizes)[:-1]), vocab.n_words)
            vocab.meta["idf_images"] = len(per_image)
        elif images is not None:
            vocab = vocab.with_idf(images)
        return vocab

    # ------------------------------------------------------------------ files
    def to_arrays(self) -> dict[str, np.ndarray]:
        """The vocabulary as named plain arrays (the ``.npz`` entries of the file format;
        also how a saved map stores it)."""
        arrays: dict[str, np.ndarray] = {
            "format": np.array(FORMAT_NAME),
            "version": np.array(FORMAT_VERSION, np.int64),
            "k": np.array(self.k, np.int64),
            "levels": np.array(self.levels, np.int64),
            "idf": self.idf,
            "meta": np.array(json.dumps(self.meta, sort_keys=True)),
        }
        for lvl, (c, v) in enumerate(zip(self._centres, self._valid), start=1):
            nodes = np.flatnonzero(v.reshape(-1)).astype(np.int64)
            arrays[f"nodes_{lvl}"] = nodes
            arrays[f"centres_{lvl}"] = np.ascontiguousarray(c.reshape(-1, 4)[nodes]).view(np.uint8).reshape(-1, 32)
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "Vocabulary":
        """Rebuild from :meth:`to_arrays`; ``ValueError`` (or ``KeyError`` for a missing
        entry) saying what is wrong: format, version, or an inconsistent tree."""
        if "format" not in arrays or "version" not in arrays:
            raise ValueError(f"not a {FORMAT_NAME} file (no format/version entries)")
        fmt = str(np.asarray(arrays["format"])[()])
        if fmt != FORMAT_NAME:
            raise ValueError(f"not a {FORMAT_NAME} file (format {fmt!r})")
        version = int(np.asarray(arrays["version"])[()])
        if version != FORMAT_VERSION:
            raise ValueError(f"vocabulary format version {version} is not supported (this dynastereo reads version {FORMAT_VERSION})")
        k, levels = int(np.asarray(arrays["k"])[()]), int(np.asarray(arrays["levels"])[()])
        if k < 2 or levels < 1 or k**levels > _MAX_SLOTS:
            raise ValueError(f"malformed vocabulary: k={k}, levels={levels}")
        centres: list[np.ndarray] = []
        valid: list[np.ndarray] = []
        for lvl in range(1, levels + 1):
            nodes = np.asarray(arrays[f"nodes_{lvl}"])
            cen = np.asarray(arrays[f"centres_{lvl}"])
            size = k**lvl
            if nodes.ndim != 1 or nodes.dtype.kind not in "iu":
                raise ValueError(f"malformed vocabulary: node ids of level {lvl} are {nodes.shape} {nodes.dtype}")
            nodes = nodes.astype(np.int64)
            if len(nodes) == 0 or nodes.min() < 0 or nodes.max() >= size or np.any(np.diff(nodes) <= 0):
                raise ValueError(f"malformed vocabulary: bad node ids at level {lvl}")
            if cen.dtype != np.uint8 or cen.shape != (len(nodes), 32):
                raise ValueError(f"malformed vocabulary: centres of level {lvl} are {cen.shape} {cen.dtype}")
            # every node hangs under a node, every node of the level above has a child
            parents = valid[-1] if valid else np.ones(1, bool)
            if not parents[nodes // k].all() or not (np.bincount(nodes // k, minlength=len(parents)) > 0)[parents].all():
                raise ValueError(f"malformed vocabulary: tree broken at level {lvl}")
            v = np.zeros(size, bool)
            v[nodes] = True
            c = np.zeros((size, 4), np.uint64)
            c[nodes] = np.ascontiguousarray(cen).view(np.uint64)
            centres.append(c)
            valid.append(v)
        idf = np.asarray(arrays["idf"])
        n_words = int(valid[-1].sum())
        if idf.dtype.kind != "f" or idf.shape != (n_words,) or not np.all(np.isfinite(idf)) or np.any(idf < 0):
            raise ValueError(f"malformed vocabulary: idf is {idf.shape} {idf.dtype} for {n_words} words")
        meta = json.loads(str(np.asarray(arrays["meta"])[()])) if "meta" in arrays else {}
        if not isinstance(meta, dict):
            raise ValueError("malformed vocabulary: meta is not a JSON object")
        return cls(k, levels, centres, valid, idf.astype(np.float64), meta)

    def save(self, path: str | Path) -> Path:
        """Write the vocabulary as a versioned ``.npz`` (format in the module docstring).
        The file is written under a temporary name and renamed: never half-written."""
        path = Path(path)
        try:
            with atomic_open(path, "wb", fsync=False, mkdir=False) as f:
                np.savez_compressed(f, **self.to_arrays())
        except OSError as e:
            raise VocabularyError(f"cannot write vocabulary: {e.strerror or e}", path) from None
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Vocabulary":
        """Read a file written by :meth:`save`; a bad file raises :class:`VocabularyError`."""
        path = Path(path)
        if not path.exists():
            raise VocabularyError("vocabulary file not found", path)
        if not path.is_file():
            raise VocabularyError("not a file", path)
        try:
            with open(path, "rb") as fh:
                magic = fh.read(6)
        except OSError as e:
            raise VocabularyError(f"cannot read it ({e.strerror or e})", path) from None
        if not (magic.startswith(b"PK") or magic.startswith(b"\x93NUMPY")):
            kind = "a text file" if magic and all(32 <= c < 127 or c in (9, 10, 13) for c in magic) else "another file"
            raise VocabularyError(f"not a {FORMAT_NAME} file ({kind}, not the .npz archive `dynastereo vocab` "
                                  "writes)", path)
        try:
            z = np.load(path, allow_pickle=False)
            if not hasattr(z, "files"):  # a .npy file: one bare array
                raise VocabularyError(f"not a {FORMAT_NAME} file (a bare .npy array, expected an .npz archive)", path)
            with z:
                arrays = {name: z[name] for name in z.files}
        except VocabularyError:
            raise
        except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as e:
            why = str(e).split(". ")[0] or type(e).__name__
            raise VocabularyError(f"corrupt or truncated vocabulary file ({why})", path) from None
        try:
            return cls.from_arrays(arrays)
        except KeyError as e:
            raise VocabularyError(f"malformed vocabulary: missing entry {e}", path) from None
        except (ValueError, TypeError, IndexError) as e:
            raise VocabularyError(str(e), path) from None

    @classmethod
    def default_path(cls) -> Path:
        """Path of the vocabulary shipped with the package."""
        return Path(str(files("dynastereo.slam") / "data" / DEFAULT_VOCABULARY))

    @classmethod
    def default(cls) -> "Vocabulary":
        """The vocabulary shipped with dynastereo: k = 12, 4 levels (20736 words, 0.75 MB),
        trained on 392 images of the synthetic generator (no file to fetch; licence-clean;
        ``benchmarks/bench_vocab.py --train-default`` remakes it).  Chosen by measurement
        (benchmarks/results/vocab.json): as good as a vocabulary trained on the sequence
        itself at retrieving KITTI places, better with distractors, and better separated
        than k = 10 (10^4 words) at the same recall."""
        return cls.load(cls.default_path())


def _idf_from_words(words_per_image: Sequence[np.ndarray], n_words: int) -> np.ndarray:
    """idf = log(N / N_w); a word in no image gets log(N) (as rare as can be)."""
    n_img = len(words_per_image)
    if n_img == 0:
        return np.ones(n_words)
    df = np.zeros(n_words, np.int64)
    for w in words_per_image:  # per image (a few hundred), vectorized within
        df[np.unique(w)] += 1
    return np.log(n_img / np.maximum(df, 1))


def _split_level(D: np.ndarray, slot: np.ndarray, k: int, rng: np.random.Generator, max_iter: int):
    """Split every node of a level at once.

    Returns ``child`` (N,) in [0, k) per descriptor and, per node present in ``slot``
    (in ``np.unique(slot)`` order), centres (G, k, 4) and valid (G, k).
    """
    groups, g = np.unique(slot, return_inverse=True)
    G, n = len(groups), len(D)
    order = np.argsort(g, kind="stable")
    gs = g[order]
    Ds = D[order]
    sizes = np.bincount(gs, minlength=G)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    C = np.zeros((G, k, 4), np.uint64)
    V = np.zeros((G, k), bool)

    # clusters of <= k descriptors: one child per descriptor
    small_g = sizes <= k
    sm = small_g[gs]
    rank = np.arange(n) - starts[gs]
    C[gs[sm], rank[sm]] = Ds[sm]
    V[gs[sm], rank[sm]] = True

    # larger clusters: k-means++ seeding, vectorized over clusters
    big = np.flatnonzero(~small_g)
    if len(big):
        bi = np.flatnonzero(~sm)  # their descriptors, still sorted by cluster
        Db, gb = Ds[bi], gs[bi]
        bstart = np.searchsorted(gb, big)
        bsize = sizes[big]
        pick = bstart + np.minimum((rng.random(len(big)) * bsize).astype(np.int64), bsize - 1)
        C[big, 0] = Db[pick]
        dmin = _hamming_rows(Db, C[gb, 0])
        for j in range(1, k):
            w = dmin.astype(np.float64) ** 2
            cs = np.cumsum(w)
            before = cs[bstart] - w[bstart]
            total = cs[bstart + bsize - 1] - before
            target = before + rng.random(len(big)) * total
            pick = np.searchsorted(cs, target, side="right")
            pick = np.clip(pick, bstart, bstart + bsize - 1)
            flat = total <= 0  # all members equal to a centre already: any member
            if flat.any():
                pick[flat] = bstart[flat] + np.minimum((rng.random(int(flat.sum())) * bsize[flat]).astype(np.int64), bsize[flat] - 1)
            C[big, j] = Db[pick]
            dmin = np.minimum(dmin, _hamming_rows(Db, C[gb, j]))
        V[big] = True

    # k-medians rounds (all clusters; small ones converge at once)
    child = np.full(n, -1, np.int64)
    for it in range(max_iter + 1):
        new = _assign(Ds, gs, C, V)
        changed = not np.array_equal(new, child)
        child = new
        if not changed or it == max_iter:
            break
        key = gs * k + child
        o = np.argsort(key, kind="stable")
        ks = key[o]
        first = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
        members = np.diff(np.r_[first, len(ks)])[:, None]
        Db = Ds[o].view(np.uint8)  # (N, 32) members grouped by child
        maj = np.empty((len(first), 32), np.uint8)
        for w in range(0, 32, 8):  # 64 bits at a time: bounded memory for millions of descriptors
            counts = np.add.reduceat(np.unpackbits(Db[:, w : w + 8], axis=1), first, axis=0, dtype=np.int32)
            maj[:, w : w + 8] = np.packbits(2 * counts >= members, axis=1)
        C.reshape(-1, 4)[ks[first]] = maj.view(np.uint64)
    # children nobody is nearest to are dropped
    used = np.zeros(G * k, bool)
    used[gs * k + child] = True
    V &= used.reshape(G, k)
    out = np.empty(n, np.int64)
    out[order] = child
    return out, C, V


def _assign(Ds: np.ndarray, gs: np.ndarray, C: np.ndarray, V: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Nearest valid centre of its cluster for every descriptor (chunks bound the memory)."""
    n = len(Ds)
    out = np.empty(n, np.int64)
    pen = np.where(V, 0, _BIG).astype(np.int32)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        g = gs[a:b]
        dist = _popsum(np.bitwise_count(C[g] ^ Ds[a:b, None, :]))
        dist += pen[g]
        out[a:b] = dist.argmin(axis=1)
    return out


def same_node_pairs(nodes_a: np.ndarray, nodes_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All index pairs ``(ia, ib)`` with ``nodes_a[ia] == nodes_b[ib]`` (ORB-SLAM2's
    SearchByBoW candidate pairs from two ``transform`` node arrays), vectorized; pairs are
    grouped by ``ia`` ascending."""
    nodes_a = np.asarray(nodes_a, np.int64)
    nodes_b = np.asarray(nodes_b, np.int64)
    if len(nodes_a) == 0 or len(nodes_b) == 0:
        z = np.zeros(0, np.int64)
        return z, z
    ob = np.argsort(nodes_b, kind="stable")
    sb = nodes_b[ob]
    lo = np.searchsorted(sb, nodes_a, side="left")
    hi = np.searchsorted(sb, nodes_a, side="right")
    cnt = hi - lo
    ia = np.repeat(np.arange(len(nodes_a)), cnt)
    offs = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    ib = ob[np.repeat(lo, cnt) + offs]
    return ia, ib


# ---------------------------------------------------------------------- from images
def collect_images(specs: Sequence[str | Path]) -> list[Path]:
    """Image files from files, folders (the images directly inside) and glob patterns
    (``**`` recurses), in the given order, sorted within a folder / pattern, duplicates
    dropped.  A missing path, an empty folder or a pattern matching no image raises
    :class:`~dynastereo.errors.InputError`."""
    out: list[Path] = []
    for spec in specs:
        p = Path(spec)
        if p.is_dir():
            imgs = list_images(p)
            if not imgs:
                raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in this folder", p)
        elif p.is_file():
            imgs = [p]
        elif any(ch in str(spec) for ch in "*?["):
            imgs = sorted(
                q for q in (Path(x) for x in glob.glob(str(spec), recursive=True)) if q.suffix.lower() in IMAGE_SUFFIXES and q.is_file()
            )
            if not imgs:
                raise InputError("the pattern matches no image files", spec)
        else:
            raise InputError("no such file or folder", p)
        out += imgs
    if not out:
        raise InputError("no images given")
    return list(dict.fromkeys(out))


def train_from_images(
    paths: Sequence[str | Path],
    k: int = 10,
    levels: int = 4,
    n_features: int = 2000,
    seed: int = 0,
    progress: Callable[[str, int, int], None] | None = None,
) -> Vocabulary:
    """Train a vocabulary on the ORB features of images (``dynastereo vocab``).

    Features come from :class:`~dynastereo.slam.orb.ORBExtractor` with the default SLAM
    settings and ``n_features`` (grayscale; what the SLAM extracts); idf weights from the
    same images.  ``progress(stage, done, total)`` with stage ``"features"`` per image and
    ``"train"`` per tree level.  An unreadable image raises
    :class:`~dynastereo.errors.ImageReadError` naming it.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise InputError("no images given")
    if n_features < 1:
        raise InputError(f"--features must be >= 1, got {n_features}")
    if k < 2 or levels < 1 or k**levels > _MAX_SLOTS:
        raise InputError(f"need k >= 2, levels >= 1 and k**levels <= {_MAX_SLOTS}, got k={k}, levels={levels}")
    c = SlamConfig()
    ex = ORBExtractor(n_features, c.scale_factor, c.n_levels, c.ini_th_fast, c.min_th_fast, c.oversample, c.mask_margin)
    descs = []
    for i, p in enumerate(paths):
        d = ex.extract(read_image(p)).desc
        if len(d):
            descs.append(d)
        if progress is not None:
            progress("features", i + 1, len(paths))
    if not descs:
        raise InputError(f"no ORB features found in the {len(paths)} image(s) (blank or tiny images?)", paths[0])
    meta = {
        "trained_on": f"{len(paths)} images, first {paths[0].name}",
        "images": len(paths),
        "features": n_features,
        "made_by": "dynastereo vocab",
    }
    cb = (lambda lvl, n: progress("train", lvl, n)) if progress is not None else None
    return Vocabulary.train(descs, k=k, levels=levels, seed=seed, progress=cb, meta=meta)
