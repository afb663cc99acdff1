"""Place recognition: which vocabulary, how well it retrieves places, and how fast.

Retrieval (recall@1 / @3).  ORB features (``ORBExtractor`` with the default SLAM
settings, 2000 features, left image) of a set of *database* frames go into a
``KeyFrameDatabase``; each *query* frame's BowVector is ranked against it
(``KeyFrameDatabase.query``, DBoW2 L1 score, the query frame itself left out).  A hit is
a database frame within ``--radius`` (5 m) of the query's ground-truth position; queries
with no database frame that close are not counted.

* ``kitti03``: database every 5th frame of 0-98 (3 m apart), queries 40-60;
* ``kitti03+distractors``: the same plus every 3rd frame of KITTI 06 and every 5th of
  the synthetic loop as distractors (61 more database frames, none a hit);
* ``kitti06``: database every 3rd frame of 0-50 (3.6 m apart; every 5th would be 6 m,
  more than the radius), queries 15-35;
* ``synth-loop``: ``dynastereo synth --scenario loop --frames 720`` (seed 0, 640x192,
  one lap is 516 frames): database every 5th frame of the first lap, queries every 2nd
  frame of the second lap (frames 520-718): a true revisit, through traffic.

Vocabularies compared:

* ``default``: the packaged one (``Vocabulary.default()``: k=12, 4 levels, 20736
  words), trained offline on the synthetic generator's images (other seeds, i.e. other
  cities, than the synth-loop test);
* ``default+idf``: its tree with idf weights recomputed from the database frames;
* ``online``: trained (k=10, L=4) on the database frames themselves: the sequence's
  own earlier keyframes;
* ``online-k10L3``: the same with 3 levels (1000 words), less thinly spread;
* ``synth-kKLL`` (``--synth-shapes``): other tree shapes trained on the default's
  synthetic images: the measurement behind the default's k and levels;
* ``bruteforce``: no vocabulary: database ranked by the number of ratio-test ORB matches
  (cv2.BFMatcher, ratio 0.8), the expensive reference (databases of <= 150 frames);
* ``chance``: expected recall of a random ranking.

Besides recall: mAP (all database frames within the radius relevant), *separation*
(median over queries of best relevant score / best other score: how far the place
stands above the rest, what a score threshold needs), AUC; and, on the synthetic loop,
ORB-SLAM2's loop-candidate step (``detect_loop_candidates``, min_score from the query's
previous keyframes): share of queries with a correct candidate, candidate precision.

Speed: ``Vocabulary.transform`` of 2000 descriptors; ``KeyFrameDatabase.add``;
``query`` and ``detect_loop_candidates`` with 100 / 500 / 2000 keyframes of 2000
descriptors each (BowVectors of real KITTI and synthetic frames, cycled); medians over
repeats.  Training time of the default vocabulary is reported by ``--train-default``.

``--train-default`` regenerates the packaged vocabulary: six synthetic sequences
(scenarios static, mixed, crossing, oncoming, convoy, loop with seeds 1-6, 1240x376,
KITTI-like size), left image of every 4th frame, k=12, L=4, seed 0 ->
``src/dynastereo/slam/data/orb_vocab_synth.npz``.

Run: DYNASTEREO_DATA=/work/shared/data .venv/bin/python benchmarks/bench_vocab.py
     [--repeats 20] [--cache DIR] [--no-bruteforce] [--train-default] [--synth-shapes 10x4,8x5,16x4]
Writes benchmarks/results/vocab.json.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from _common import ROOT, data_dir, machine, median_ms, results_path, write_json
from dynastereo.config import SlamConfig
from dynastereo.io.images import read_image
from dynastereo.slam.keyframe_database import KeyFrameDatabase
from dynastereo.slam.orb import ORBExtractor
from dynastereo.slam.vocabulary import BowVector, Vocabulary

OUT = results_path("vocab")
DEFAULT_FILE = ROOT / "src" / "dynastereo" / "slam" / "data" / "orb_vocab_synth.npz"
TRAIN_SCENARIOS = ("static", "mixed", "crossing", "oncoming", "convoy", "loop")
DEFAULT_K, DEFAULT_LEVELS = 12, 4


def extractor() -> ORBExtractor:
    c = SlamConfig()
    return ORBExtractor(c.n_features, c.scale_factor, c.n_levels, c.ini_th_fast, c.min_th_fast, c.oversample, c.mask_margin)


def extract(paths: list[Path], cache: Path | None, name: str) -> list[np.ndarray]:
    """Left-image ORB descriptors per path (cached as DIR/name.npz when --cache)."""
    f = cache / f"{name}.npz" if cache else None
    if f is not None and f.exists():
        z = np.load(f)
        return np.split(z["desc"], z["ptr"][1:-1])
    ex = extractor()
    descs = [ex.extract(read_image(p)).desc for p in paths]
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        np.savez(f, desc=np.concatenate(descs), ptr=np.r_[0, np.cumsum([len(d) for d in descs])])
    return descs


def kitti_centres(data: Path, seq: str, n: int) -> np.ndarray:
    P = np.loadtxt(data / "kitti_odometry/dataset/poses" / f"{seq}.txt")[:n].reshape(-1, 3, 4)
    return P[:, :, 3]


def generate(out: Path, scenario: str, seed: int, frames: int | None = None, size=(640, 192)) -> Path:
    from dynastereo.synth import generate as synth_generate

    root = out / f"{scenario}_s{seed}_{size[0]}x{size[1]}_{frames}"
    seq = root / "sequences" / "00"
    if not (seq / "image_0").exists() or not (root / "poses" / "00.txt").exists():
        synth_generate(root, scenario, frames=frames, seed=seed, size=size)
    return root


# ---------------------------------------------------------------------- data sets
class Dataset:
    def __init__(self, name, desc, centres, db, queries, distract=None):
        self.name, self.desc, self.centres, self.db, self.queries = name, desc, centres, list(db), list(queries)
        self.distract = distract or []  # extra database descriptor sets, never a hit


def load_datasets(data: Path | None, work: Path, cache: Path | None) -> list[Dataset]:
    sets = []
    loop = generate(work, "loop", 0, 720)
    n_loop = len(sorted((loop / "sequences/00/image_0").glob("*.png")))
    loop_desc = extract(sorted((loop / "sequences/00/image_0").glob("*.png")), cache, "synth_loop_720")
    loop_c = np.loadtxt(loop / "poses/00.txt").reshape(-1, 3, 4)[:, :, 3]
    if data is not None:
        d03 = data / "kitti_odometry/dataset/sequences/03/image_0"
        d06 = data / "kitti_odometry/dataset/sequences/06/image_0"
        k03 = extract([d03 / f"{i:06d}.png" for i in range(99)], cache, "kitti03")
        k06 = extract([d06 / f"{i:06d}.png" for i in range(51)], cache, "kitti06")
        c03, c06 = kitti_centres(data, "03", 99), kitti_centres(data, "06", 51)
        sets.append(Dataset("kitti03", k03, c03, range(0, 99, 5), range(40, 61)))
        distract = [k06[i] for i in range(0, 51, 3)] + [loop_desc[i] for i in range(0, 516, 12)]
        sets.append(Dataset("kitti03+distractors", k03, c03, range(0, 99, 5), range(40, 61), distract))
        sets.append(Dataset("kitti06", k06, c06, range(0, 51, 3), range(15, 36)))
    else:
        print("DYNASTEREO_DATA not set: KITTI rows skipped", file=sys.stderr)
    sets.append(Dataset("synth-loop", loop_desc, loop_c, range(0, 516, 5), range(520, min(n_loop, 720), 2)))
    # other cities of the same generator (seeds 7, 8: not in the default's training set) as
    # distractors: same textures and objects, other layouts -- perceptual aliasing
    distract = []
    for sc, seed in (("mixed", 7), ("static", 8)):
        root = generate(work, sc, seed)
        paths = sorted((root / "sequences/00/image_0").glob("*.png"))[::3]
        distract += extract(paths, cache, f"distract_{sc}_s{seed}")
    if data is not None:
        distract += [k03[i] for i in range(0, 99, 5)] + [k06[i] for i in range(0, 51, 3)]
    sets.append(Dataset("synth-loop+distractors", loop_desc, loop_c, range(0, 516, 5), range(520, min(n_loop, 720), 2), distract))
    return sets


# ---------------------------------------------------------------------- retrieval
def rank_bow(vocab: Vocabulary, ds: Dataset) -> list[list[tuple[int, float]]]:
    """Per query: ``(database frame id, score)`` ranked by BoW score (query frame left
    out); distractors get ids >= 10**6."""
    db = KeyFrameDatabase(vocab)
    for i in ds.db:
        db.add(i, vocab.transform(ds.desc[i])[0])
    for j, d in enumerate(ds.distract):
        db.add(10**6 + j, vocab.transform(d)[0])
    out = []
    for q in ds.queries:
        bow = vocab.transform(ds.desc[q])[0]
        ranked = db.query(bow, exclude=(q,), top=len(db))
        seen = {k for k, _ in ranked}  # frames sharing no word: score 0, at the end
        out.append(ranked + [(k, 0.0) for k in db.ids() if k not in seen and k != q])
    return out


def loop_detection(vocab: Vocabulary, ds: Dataset, radius: float) -> dict:
    """ORB-SLAM2's loop-candidate step on the second lap: ``detect_loop_candidates`` with
    min_score = the query's lowest score against its two previous keyframes (5 and 10
    frames back, standing in for its covisible keyframes), covisibility = database
    neighbours 5 and 10 frames apart.  Reports the share of queries with a candidate,
    with a correct one (within the radius), and the share of correct candidates."""
    db = KeyFrameDatabase(vocab)
    for i in ds.db:
        db.add(i, vocab.transform(ds.desc[i])[0])
    for j, d in enumerate(ds.distract):
        db.add(10**6 + j, vocab.transform(d)[0])

    def covis(i: int) -> list[int]:
        step = 1 if i >= 10**6 else 5
        return [j for j in (i - step, i + step, i - 2 * step, i + 2 * step) if j in db]

    any_c = good_q = n_c = good_c = n = 0
    for q in ds.queries:
        pos = positives(ds, q, radius)
        if not pos:
            continue
        n += 1
        bow = vocab.transform(ds.desc[q])[0]
        min_score = min(vocab.score(bow, vocab.transform(ds.desc[q - s])[0]) for s in (5, 10))
        cands = db.detect_loop_candidates(q, bow, set(), min_score, covis)
        ok = [c in pos for c in cands]
        any_c += bool(cands)
        good_q += any(ok)
        n_c += len(cands)
        good_c += sum(ok)
    return {"queries": n, "with_candidate": any_c / max(n, 1), "with_correct": good_q / max(n, 1),
            "candidate_precision": good_c / max(n_c, 1), "candidates_per_query": n_c / max(n, 1)}


def rank_bruteforce(ds: Dataset) -> list[list[tuple[int, float]]]:
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    ids = list(ds.db) + [10**6 + j for j in range(len(ds.distract))]
    descs = [ds.desc[i] for i in ds.db] + list(ds.distract)
    out = []
    for q in ds.queries:
        counts = []
        for i, d in zip(ids, descs):
            if i == q:
                counts.append(-1)
                continue
            m = bf.knnMatch(ds.desc[q], d, k=2)
            counts.append(sum(1 for p in m if len(p) == 2 and p[0].distance < 0.8 * p[1].distance))
        o = np.argsort(-np.array(counts), kind="stable")
        out.append([(ids[i], float(counts[i])) for i in o if ids[i] != q])
    return out


def positives(ds: Dataset, q: int, radius: float) -> set[int]:
    return {i for i in ds.db if i != q and np.linalg.norm(ds.centres[i] - ds.centres[q]) <= radius}


def recall(ds: Dataset, ranked: list[list[tuple[int, float]]], radius: float) -> dict:
    """recall@1, recall@3; mean average precision (all database frames within the radius
    are relevant: mAP also rewards ranking the second and third close frames high);
    ``separation``: median over queries of best relevant score / best other score (how
    far above the rest the place stands: what a score threshold needs); ``auc``: mean
    over queries of P(a relevant frame scores above an other one)."""
    hits1 = hits3 = n = 0
    aps, seps, aucs = [], [], []
    for q, rs in zip(ds.queries, ranked):
        pos = positives(ds, q, radius)
        if not pos:
            continue
        n += 1
        r = [k for k, _ in rs]
        sc = np.array([v for _, v in rs])
        hits1 += bool(r[:1]) and r[0] in pos
        hits3 += any(i in pos for i in r[:3])
        rel = np.array([i in pos for i in r], bool)
        prec = np.cumsum(rel) / np.arange(1, len(r) + 1)
        aps.append(float((prec * rel).sum() / len(pos)))
        if (~rel).any():
            sp, sn = sc[rel], sc[~rel]
            seps.append(sp.max() / max(sn.max(), 1e-9))
            aucs.append(float(((sp[:, None] > sn[None, :]) + 0.5 * (sp[:, None] == sn[None, :])).mean()))
    return {"recall@1": hits1 / max(n, 1), "recall@3": hits3 / max(n, 1), "mAP": float(np.mean(aps)) if aps else 0.0,
            "separation": float(np.median(seps)) if seps else float("nan"), "auc": float(np.mean(aucs)) if aucs else float("nan"),
            "queries": n}


def chance(ds: Dataset, radius: float) -> dict:
    r1, r3, n = [], [], 0
    for q in ds.queries:
        cand = [i for i in ds.db if i != q] + [10**6 + j for j in range(len(ds.distract))]
        p = sum(1 for i in cand if i < 10**6 and np.linalg.norm(ds.centres[i] - ds.centres[q]) <= radius)
        if p == 0:
            continue
        n += 1
        m = len(cand)
        r1.append(p / m)
        # P(at least one of p positives in a random top 3 of m)
        miss = 1.0
        for t in range(3):
            miss *= max(0.0, (m - p - t) / (m - t))
        r3.append(1 - miss)
    return {"recall@1": float(np.mean(r1)) if r1 else 0.0, "recall@3": float(np.mean(r3)) if r3 else 0.0, "mAP": float("nan"),
            "separation": 1.0, "auc": 0.5, "queries": n}


def retrieval(sets: list[Dataset], radius: float, bruteforce: bool, extra: dict[str, Vocabulary] | None = None) -> list[dict]:
    rows = []
    default = Vocabulary.default()
    for ds in sets:
        train_imgs = [ds.desc[i] for i in ds.db]
        t = time.perf_counter()
        online = Vocabulary.train(train_imgs, k=10, levels=4, seed=0)
        t_online = time.perf_counter() - t
        online3 = Vocabulary.train(train_imgs, k=10, levels=3, seed=0)
        options = {
            "default": default,
            "default+idf": default.with_idf(train_imgs),
            "online": online,
            "online-k10L3": online3,
            **(extra or {}),
        }
        for name, voc in options.items():
            r = recall(ds, rank_bow(voc, ds), radius)
            r.update(dataset=ds.name, vocabulary=name, words=voc.n_words)
            if name == "online":
                r["train_s"] = round(t_online, 2)
            if ds.name.startswith("synth-loop"):
                r["loop_detection"] = loop_detection(voc, ds, radius)
            rows.append(r)
        if bruteforce and len(ds.db) + len(ds.distract) <= 150:
            r = recall(ds, rank_bruteforce(ds), radius)
            r.update(dataset=ds.name, vocabulary="bruteforce", words=0)
            rows.append(r)
        r = chance(ds, radius)
        r.update(dataset=ds.name, vocabulary="chance", words=0)
        rows.append(r)
    return rows


# ---------------------------------------------------------------------- speed
def med_ms(f, repeats: int) -> float:
    return median_ms(f, repeats)


def speed(vocab: Vocabulary, pool: list[np.ndarray], repeats: int, sizes=(100, 500, 2000)) -> list[dict]:
    rows = []
    d2000 = [d for d in pool if len(d) >= 1900]
    rows.append({"what": "transform (2000 descriptors)", "n_keyframes": 0,
                 "ms": med_ms(lambda: vocab.transform(d2000[0]), repeats * 5)})
    rows.append({"what": "words_of (2000 descriptors)", "n_keyframes": 0,
                 "ms": med_ms(lambda: vocab.words_of(d2000[0]), repeats * 5)})
    bows = [vocab.transform(d)[0] for d in pool]
    rows.append({"what": "BowVector words per frame (median)", "n_keyframes": 0, "ms": float(np.median([len(b) for b in bows])), "unit": "words"})
    rng = np.random.default_rng(0)

    def covis(i: int) -> list[int]:  # temporal neighbours stand in for the covisibility graph
        return [j for j in (i - 1, i + 1, i - 2, i + 2, i - 3, i + 3) if j >= 0]

    for n in sizes:
        db = KeyFrameDatabase(vocab)
        t = time.perf_counter()
        for i in range(n):
            db.add(i, bows[i % len(bows)])
        add_ms = (time.perf_counter() - t) * 1000 / n
        qs = [int(q) for q in rng.integers(0, len(bows), repeats)]
        tq, tl, tr = [], [], []
        for q in qs:
            b = bows[q]
            t0 = time.perf_counter()
            db.query(b, exclude=(q,), top=10)
            t1 = time.perf_counter()
            db.detect_loop_candidates(q, b, set(range(q - 5, q + 6)), 0.01, covis)
            t2 = time.perf_counter()
            db.detect_relocalization_candidates(b, covis)
            t3 = time.perf_counter()
            tq.append(t1 - t0)
            tl.append(t2 - t1)
            tr.append(t3 - t2)
        rows.append({"what": "add (amortized, incl. index merges)", "n_keyframes": n, "ms": add_ms})
        rows.append({"what": "query top 10", "n_keyframes": n, "ms": float(np.median(tq) * 1000)})
        rows.append({"what": "detect_loop_candidates", "n_keyframes": n, "ms": float(np.median(tl) * 1000)})
        rows.append({"what": "detect_relocalization_candidates", "n_keyframes": n, "ms": float(np.median(tr) * 1000)})
        rows.append({"what": "postings in the index", "n_keyframes": n, "ms": float(db.n_postings), "unit": "postings"})
    return rows


# ---------------------------------------------------------------------- default
def synth_training_set(work: Path, cache: Path | None, step: int = 4) -> list[np.ndarray]:
    """Descriptors of the left image of every ``step``-th frame of the six synthetic
    training sequences (scenarios x seeds 1-6, 1240x376), generated if absent."""
    descs = []
    for i, sc in enumerate(TRAIN_SCENARIOS, start=1):
        root = generate(work, sc, i, None, (1240, 376))
        paths = sorted((root / "sequences/00/image_0").glob("*.png"))[::step]
        descs += extract(paths, cache, f"train_{sc}_s{i}_step{step}")
    return descs


def train_default(work: Path, cache: Path | None, out: Path = DEFAULT_FILE, step: int = 4) -> dict:
    t0 = time.perf_counter()
    descs = synth_training_set(work, cache, step)
    t_data = time.perf_counter() - t0
    meta = {
        "trained_on": f"dynastereo synth 1240x376, left image of every {step}th frame: "
        + ", ".join(f"{sc} seed {i}" for i, sc in enumerate(TRAIN_SCENARIOS, start=1)),
        "features": "ORBExtractor, SlamConfig defaults (2000 features, 8 levels, scale 1.2)",
        "images": len(descs),
        "made_by": "benchmarks/bench_vocab.py --train-default",
    }
    t0 = time.perf_counter()
    voc = Vocabulary.train(descs, k=DEFAULT_K, levels=DEFAULT_LEVELS, seed=0, meta=meta)
    t_train = time.perf_counter() - t0
    out.parent.mkdir(parents=True, exist_ok=True)
    voc.save(out)
    info = {"file": str(out.relative_to(ROOT)), "bytes": out.stat().st_size, "images": len(descs),
            "descriptors": int(sum(len(d) for d in descs)), "k": DEFAULT_K, "levels": DEFAULT_LEVELS,
            "words": voc.n_words, "train_s": round(t_train, 1), "data_s": round(t_data, 1), "fingerprint": voc.fingerprint}
    print(f"default vocabulary: {info}", file=sys.stderr)
    return info


def synth_shapes(spec: str, work: Path, cache: Path | None) -> dict[str, Vocabulary]:
    """Vocabularies of other shapes trained on the default's synthetic images
    (``--synth-shapes 10x4,16x4``): the measurement behind the default's k and levels."""
    out: dict[str, Vocabulary] = {}
    if not spec:
        return out
    descs = synth_training_set(work, cache)
    for item in spec.split(","):
        k, levels = (int(x) for x in item.lower().split("x"))
        t0 = time.perf_counter()
        v = Vocabulary.train(descs, k=k, levels=levels, seed=0)
        with tempfile.TemporaryDirectory() as d:
            size = v.save(Path(d) / "v.npz").stat().st_size
        out[f"synth-k{k}L{levels}"] = v
        print(f"  synth k={k} L={levels}: {v.n_words} words, {size / 1e6:.2f} MB, trained in {time.perf_counter() - t0:.0f} s",
              file=sys.stderr)
        v.meta["file_bytes"] = size
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--radius", type=float, default=5.0)
    ap.add_argument("--cache", type=Path, default=None, help="keep generated sequences and descriptors here")
    ap.add_argument("--no-bruteforce", action="store_true")
    ap.add_argument("--train-default", action="store_true", help="regenerate the packaged default vocabulary first")
    ap.add_argument("--synth-shapes", default="", help="also compare synthetic vocabularies of these shapes, e.g. 10x4,16x4")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    data = data_dir(required=False)
    tmp = None
    if a.cache is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_vocab_")
        work, cache = Path(tmp.name), None
    else:
        work, cache = a.cache, a.cache / "desc"
    result: dict = {"benchmark": "vocab", "repeats": a.repeats, "radius_m": a.radius,
                    "machine": machine()}
    if a.train_default:
        result["default_training"] = train_default(work, cache)
    default = Vocabulary.default()
    result["default_vocabulary"] = {"words": default.n_words, "k": default.k, "levels": default.levels,
                                    "bytes": Vocabulary.default_path().stat().st_size, "meta": default.meta}
    extra = synth_shapes(a.synth_shapes, work, cache)
    result["synth_shapes"] = {n: {"words": v.n_words, "bytes": v.meta["file_bytes"]} for n, v in extra.items()}
    sets = load_datasets(data, work, cache)
    rows = retrieval(sets, a.radius, not a.no_bruteforce, extra)
    result["retrieval"] = rows
    print(f"\nretrieval: recall@1 / recall@3 / mAP / separation (hit = database frame within {a.radius:g} m)")
    names = list(dict.fromkeys(r["vocabulary"] for r in rows))
    for ds in dict.fromkeys(r["dataset"] for r in rows):
        cells = {r["vocabulary"]: r for r in rows if r["dataset"] == ds}
        q = next(iter(cells.values()))["queries"]
        print(f"  {ds} ({q} queries)")
        for n in names:
            if n in cells:
                c = cells[n]
                w = f"{c['words']} words" if c["words"] else ""
                print(f"    {n:16s} {w:>12s}  {c['recall@1']:5.2f} / {c['recall@3']:4.2f} / {c['mAP']:5.3f} / {c['separation']:5.2f}")
    print("\nloop detection (synthetic loop, second lap): with candidate / with correct / candidate precision")
    for r in rows:
        if "loop_detection" in r:
            ld = r["loop_detection"]
            print(f"  {r['dataset']:24s} {r['vocabulary']:14s} {ld['with_candidate']:5.2f} / {ld['with_correct']:5.2f} / "
                  f"{ld['candidate_precision']:5.2f}   ({ld['candidates_per_query']:.1f} candidates per query)")
    pool = [d for ds in sets for d in ds.desc]
    srows = speed(default, pool, a.repeats)
    result["speed"] = srows
    print("\nspeed (median ms; default vocabulary)")
    for r in srows:
        unit = r.get("unit", "ms")
        print(f"  {r['what']:40s} {('n=' + str(r['n_keyframes'])) if r['n_keyframes'] else '':8s} {r['ms']:10.3f} {unit}")
    write_json(a.out, result)
    print(f"\nwrote {a.out}")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
