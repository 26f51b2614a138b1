"""ORB bag-of-words vocabularies in the DBoW2 text format that ORB-SLAM3 loads (`ORBvoc.txt`).

ORB-SLAM3 needs a vocabulary for relocalisation and loop detection; the official 139 MB file is a
download this project cannot rely on, so we train our own from images. The tree is DBoW2's:
hierarchical k-majority clustering (k-medians on bits) with k-means++ seeding, `levels` deep,
leaves are the words, each weighted by its inverse document frequency ln(N / N_i) over the
training images. Training is vectorised NumPy and deterministic: the same images, parameters and
seed give a byte-identical file.

Text format (DBoW2 `TemplatedVocabulary::saveToTextFile` / `loadFromTextFile`):

    k L  scoring weighting                        first line, e.g. "10 6  0 0" (L1 norm, TF-IDF)
    parent is_leaf d0 d1 ... d31  weight          one line per node, node ids 1, 2, ... in order

Node 0 is the root and has no line; a node's parent always comes before it (depth-first order, the
order DBoW2's HKmeansStep creates nodes in); inner nodes have weight 0. We write no newline after
the last node: ORB-SLAM3's loader reads `while (!f.eof())`, so a trailing newline would add a
bogus empty node under the root (the official ORBvoc.txt has one; it is harmless there only by luck).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.opencv import baseline_simd

DESCRIPTOR_BYTES = 32
SCORING_L1 = 0  # DBoW2 ScoringType L1_NORM
WEIGHTING_TF_IDF = 0  # DBoW2 WeightingType TF_IDF
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp")
_FAR = 1 << 10  # larger than any Hamming distance of 256 bits


@dataclass(frozen=True, eq=False)
class Vocabulary:
    """A vocabulary tree. Arrays are indexed by node id; node 0 is the root."""

    k: int
    levels: int
    parents: np.ndarray  # (n,) int64, -1 for the root
    is_leaf: np.ndarray  # (n,) bool
    descriptors: np.ndarray  # (n, 32) uint8 (root: zeros)
    weights: np.ndarray  # (n,) float64, IDF of words, 0 for inner nodes
    scoring: int = SCORING_L1
    weighting: int = WEIGHTING_TF_IDF

    @property
    def n_nodes(self) -> int:
        """Nodes without the root (the number of lines after the header)."""
        return int(self.parents.shape[0]) - 1

    @property
    def word_nodes(self) -> np.ndarray:
        """Node id of each word, in word-id order (DBoW2 numbers leaves by node id)."""
        leaf = self.is_leaf.copy()
        leaf[0] = False
        return np.flatnonzero(leaf)

    @property
    def n_words(self) -> int:
        return int(self.word_nodes.shape[0])

    def children_table(self) -> np.ndarray:
        """(n, k) child node ids in creation order, -1 padded."""
        n = self.parents.shape[0]
        width = max(1, self.k)
        table = np.full((n, width), -1, dtype=np.int64)
        fill = np.zeros(n, dtype=np.int64)
        for nid in range(1, n):
            p = int(self.parents[nid])
            table[p, fill[p]] = nid
            fill[p] += 1
        return table

    def transform_nodes(self, desc: np.ndarray, table: np.ndarray | None = None) -> np.ndarray:
        """Leaf node reached by each descriptor descending greedily (nearest child, first on ties)."""
        d = _as_u64(desc)
        table = self.children_table() if table is None else table
        nodes_u64 = _as_u64(self.descriptors)
        cur = np.zeros(d.shape[0], dtype=np.int64)
        active = np.flatnonzero(~self.is_leaf[cur])
        while active.size:
            ch = table[cur[active]]  # (m, k)
            valid = ch >= 0
            dist = _hamming_rows(d[active], nodes_u64[np.where(valid, ch, 0)])
            dist = np.where(valid, dist, _FAR)
            best = ch[np.arange(active.size), np.argmin(dist, axis=1)]
            cur[active] = best
            active = active[~self.is_leaf[best]]
        return cur

    def transform(self, desc: np.ndarray) -> np.ndarray:
        """Word id of each descriptor (DBoW2 `transform`)."""
        word_of_node = np.full(self.parents.shape[0], -1, dtype=np.int64)
        word_of_node[self.word_nodes] = np.arange(self.n_words)
        return word_of_node[self.transform_nodes(desc)]

    def to_text(self) -> str:
        lines = [f"{self.k} {self.levels}  {self.scoring} {self.weighting}"]
        for nid in range(1, self.parents.shape[0]):
            d = " ".join(str(int(b)) for b in self.descriptors[nid])
            lines.append(f"{int(self.parents[nid])} {int(self.is_leaf[nid])} {d}  {_fmt_weight(self.weights[nid])}")
        return "\n".join(lines)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the text file (atomically: a half-written vocabulary would abort ORB-SLAM3)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".part")
        try:
            tmp.write_text(self.to_text(), encoding="ascii")
            os.replace(tmp, path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise InputError(f"cannot write vocabulary {path}: {exc.strerror or exc}") from None
        return path


def _fmt_weight(w: float) -> str:
    # C++ ostream default for a double (6 significant digits, %g), as DBoW2 writes it
    return "0" if w == 0.0 else f"{float(w):.6g}"


def _as_u64(desc: np.ndarray) -> np.ndarray:
    d = np.ascontiguousarray(desc, dtype=np.uint8)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
        raise ValueError(f"want (N, {DESCRIPTOR_BYTES}) uint8 ORB descriptors, got {d.shape}")
    return d.view(np.uint64)


def _hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (m, 4) u64 against b (m, c, 4) u64 -> (m, c) distances."""
    return np.bitwise_count(a[:, None, :] ^ b).sum(axis=2, dtype=np.int64)


def _hamming_to(a: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """a (n, 4) u64 against centers (c, 4) u64 -> (n, c) distances."""
    return np.bitwise_count(a[:, None, :] ^ centers[None, :, :]).sum(axis=2, dtype=np.int64)


# ----------------------------------------------------------------------------------------------
# Reading


def parse(text: str, source: str = "<string>") -> Vocabulary:
    """A vocabulary from DBoW2 text; errors name the file and line."""
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()  # a trailing newline (the official ORBvoc.txt has one) ends the last line
    return _parse_lines(iter(lines), len(lines), source)


def _parse_lines(lines: Iterator[str], n: int, source: str) -> Vocabulary:
    """The `n` lines of a DBoW2 text vocabulary, read one at a time (a file's lines are never all held)."""
    first = next(lines, None)
    if first is None or n == 0:
        raise InputError(f"{source}: empty vocabulary file")
    head = first.split()
    try:
        k, levels, scoring, weighting = (int(x) for x in head)
    except ValueError:
        raise InputError(f"{source}: line 1 {first[:40]!r}: want 'k L scoring weighting'") from None
    if not (0 < k <= 20 and 1 <= levels <= 10 and 0 <= scoring <= 5 and 0 <= weighting <= 3):
        raise InputError(f"{source}: line 1: k={k} L={levels} scoring={scoring} weighting={weighting} "
                         "out of DBoW2's range (k 1..20, L 1..10)")
    parents = np.full(n, -1, dtype=np.int64)
    is_leaf = np.zeros(n, dtype=bool)
    descs = np.zeros((n, DESCRIPTOR_BYTES), dtype=np.uint8)
    weights = np.zeros(n, dtype=np.float64)
    for nid, line in enumerate(lines, 1):
        parts = line.split()
        try:
            if len(parts) != DESCRIPTOR_BYTES + 3 or nid >= n:
                raise ValueError
            p, leaf = int(parts[0]), int(parts[1])
            d = [int(x) for x in parts[2 : 2 + DESCRIPTOR_BYTES]]
            w = float(parts[-1])
            if not (0 <= p < nid) or leaf not in (0, 1) or min(d) < 0 or max(d) > 255:
                raise ValueError
        except ValueError:
            raise InputError(f"{source}: line {nid + 1}: want 'parent is_leaf d0..d31 weight' "
                             f"with parent < {nid}") from None
        parents[nid], is_leaf[nid], weights[nid] = p, bool(leaf), w
        descs[nid] = d
    # a node without children is a leaf whatever its flag says (DBoW2: children.empty())
    has_children = np.zeros(n, dtype=bool)
    has_children[parents[1:]] = True
    if np.any(is_leaf & has_children):
        bad = int(np.flatnonzero(is_leaf & has_children)[0])
        raise InputError(f"{source}: line {bad + 1}: node {bad} is marked a leaf but has children")
    return Vocabulary(k, levels, parents, ~has_children, descs, weights, scoring, weighting)


def load(path: str | os.PathLike[str]) -> Vocabulary:
    """Read a DBoW2 text vocabulary line by line: the official ORBvoc.txt is 145 MB of text, and
    holding it whole (plus its split lines) would more than double the tracker's peak memory."""
    path = Path(path)
    try:
        n, last = 0, b"\n"
        with open(path, "rb") as f:  # count the lines first: the arrays are made once, at their size
            for chunk in iter(lambda: f.read(1 << 20), b""):
                n, last = n + chunk.count(b"\n"), chunk[-1:]
        n += last != b"\n"  # a last line without its newline
        with open(path, encoding="ascii") as f:
            return _parse_lines((line.rstrip("\n") for line in f), n, str(path))
    except FileNotFoundError:
        raise InputError(f"vocabulary {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"vocabulary {path}: cannot read it ({exc})") from None


def check_header(path: str | os.PathLike[str]) -> None:
    """Cheap check that a file starts and ends like a DBoW2 text vocabulary, without parsing it all:
    ORB-SLAM3 exits the process on a header it cannot read, and silently loads a truncated file."""
    try:
        with open(path, "rb") as f:
            first = f.readline(256).decode("ascii", "replace")
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - 1024))
            tail = f.read().decode("ascii", "replace")
    except OSError as exc:
        raise InputError(f"vocabulary {path}: cannot read it ({exc.strerror or exc})") from None
    parts = first.split()
    ok = len(parts) == 4 and all(p.isdigit() for p in parts)
    if ok:
        k, levels, scoring, weighting = (int(p) for p in parts)
        ok = 0 < k <= 20 and 1 <= levels <= 10 and scoring <= 5 and weighting <= 3
    if not ok:
        raise InputError(f"vocabulary {path}: not a DBoW2 text vocabulary (first line {first.strip()[:40]!r}, "
                         "want 'k L scoring weighting'); build one with `octolog vocab build`")
    lines = tail.strip().split("\n")
    if len(lines) < 2 or len(lines[-1].split()) != DESCRIPTOR_BYTES + 3:
        raise InputError(f"vocabulary {path}: the last line is not a whole node "
                         "('parent is_leaf d0..d31 weight'): a truncated file?")


# ----------------------------------------------------------------------------------------------
# Training


def train(
    descriptor_sets: Sequence[np.ndarray],
    *,
    k: int = 10,
    levels: int = 6,
    seed: int = 0,
    max_iterations: int = 30,
) -> Vocabulary:
    """Train a vocabulary on per-image descriptor sets ((N_i, 32) uint8 each)."""
    _check_params(k, levels, seed)
    sets = [np.ascontiguousarray(d, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES) for d in descriptor_sets]
    all_desc = np.concatenate(sets) if sets else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    if all_desc.shape[0] < k:
        raise InputError(f"only {all_desc.shape[0]} descriptors to train on: want at least k={k}")
    d64 = all_desc.view(np.uint64)
    rng = np.random.default_rng(seed)

    parents: list[int] = [-1]
    descs: list[np.ndarray] = [np.zeros(DESCRIPTOR_BYTES, np.uint8)]
    has_children: list[bool] = [False]

    def step(parent: int, idx: np.ndarray, level: int) -> None:
        if idx.size <= k:
            centers = all_desc[idx]
            groups = [idx[i : i + 1] for i in range(idx.size)]
        else:
            centers, groups = _kmajority(all_desc, d64, idx, k, rng, max_iterations)
        first = len(parents)
        for c in range(len(groups)):
            parents.append(parent)
            descs.append(centers[c])
            has_children.append(False)
        has_children[parent] = True
        if level < levels:
            for c, g in enumerate(groups):
                if g.size > 1:
                    step(first + c, g, level + 1)

    step(0, np.arange(all_desc.shape[0]), 1)
    n = len(parents)
    is_leaf = ~np.array(has_children)
    is_leaf[0] = False
    voc = Vocabulary(k, levels, np.array(parents, dtype=np.int64), is_leaf, np.array(descs, dtype=np.uint8),
                     np.zeros(n, dtype=np.float64))
    # IDF weights: ln(N / N_i), N_i = training images in which word i occurs (DBoW2 setNodeWeights)
    table = voc.children_table()
    seen = np.zeros(n, dtype=np.int64)
    for s in sets:
        if s.shape[0]:
            seen[np.unique(voc.transform_nodes(s, table))] += 1
    weights = np.zeros(n, dtype=np.float64)
    used = is_leaf & (seen > 0)
    weights[used] = np.log(len(sets) / seen[used])
    return Vocabulary(k, levels, voc.parents, is_leaf, voc.descriptors, weights)


def _check_params(k: int, levels: int, seed: int) -> None:
    if not 2 <= k <= 20:
        raise InputError(f"vocabulary k={k}: want 2..20 (DBoW2's loader accepts up to 20)")
    if not 1 <= levels <= 10:
        raise InputError(f"vocabulary levels={levels}: want 1..10")
    if seed < 0:
        raise InputError(f"vocabulary seed {seed}: want >= 0")


def _kmajority(all_desc: np.ndarray, d64: np.ndarray, idx: np.ndarray, k: int, rng: np.random.Generator,
               max_iterations: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """k-medians on bits of the descriptors `idx`: (centers (c, 32) uint8, member indices per centre)."""
    x = d64[idx]
    n = idx.size
    # Greedy k-means++ seeding: draw `trials` candidates with probability proportional to the
    # squared Hamming distance to the nearest centre so far and keep the one that lowers the total
    # most (DBoW2 draws one candidate by plain distance, which often seeds two centres in one
    # cluster that k-medians cannot separate again). Integer weights: no float summation order.
    trials = 2 + int(math.log(k))
    chosen = [int(rng.integers(n))]
    min_d = _hamming_to(x, x[chosen[0]][None, :])[:, 0]
    while len(chosen) < k:
        w = min_d * min_d
        total = int(w.sum())
        if total == 0:
            break  # every descriptor equals a centre already
        cuts = rng.integers(1, total + 1, size=trials)
        cand = np.searchsorted(np.cumsum(w), cuts, side="left")
        d_new = np.minimum(min_d[:, None], _hamming_to(x, x[cand]))  # (n, trials)
        best = int(np.argmin((d_new * d_new).sum(axis=0)))  # first on ties
        chosen.append(int(cand[best]))
        min_d = d_new[:, best]
    centers = all_desc[idx[chosen]]
    assign = np.argmin(_hamming_to(x, centers.view(np.uint64)), axis=1)
    bits = np.unpackbits(all_desc[idx], axis=1)  # (n, 256), MSB first like DBoW2's FORB
    for _ in range(max_iterations):
        centers = _majority(bits, assign, centers.shape[0], centers)
        new = np.argmin(_hamming_to(x, centers.view(np.uint64)), axis=1)
        if np.array_equal(new, assign):
            break
        assign = new
    order = np.argsort(assign, kind="stable")
    counts = np.bincount(assign, minlength=centers.shape[0])
    split = np.split(idx[order], np.cumsum(counts)[:-1])
    keep = [c for c in range(centers.shape[0]) if counts[c] > 0]  # a centre can lose all members
    return centers[keep], [split[c] for c in keep]


def _majority(bits: np.ndarray, assign: np.ndarray, m: int, old: np.ndarray) -> np.ndarray:
    """Per cluster, each bit set iff at least half the members have it (DBoW2 FORB::meanValue)."""
    out = old.copy()
    counts = np.bincount(assign, minlength=m)
    order = np.argsort(assign, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    nonempty = np.flatnonzero(counts)
    sums = np.add.reduceat(bits[order], starts[nonempty], axis=0, dtype=np.int32)
    out[nonempty] = np.packbits(2 * sums >= counts[nonempty, None], axis=1)
    return out


# ----------------------------------------------------------------------------------------------
# Images → descriptors


def list_images(folders: Sequence[str | os.PathLike[str]], max_images: int | None = None) -> list[Path]:
    """Image files of the folders, sorted by name per folder; `max_images` evenly spaced ones."""
    files: list[Path] = []
    for folder in folders:
        p = Path(folder)
        if not p.is_dir():
            raise InputError(f"{p}: not a folder of images")
        found = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and f.is_file())
        if not found:
            raise InputError(f"{p}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
        files.extend(found)
    if max_images is not None:
        if max_images < 1:
            raise InputError(f"max_images {max_images}: want >= 1")
        if len(files) > max_images:
            pick = np.linspace(0, len(files) - 1, max_images).round().astype(int)
            files = [files[i] for i in pick]
    return files


def extract(files: Sequence[Path], *, n_features: int = 1000,
            progress: Callable[[int, int], None] | None = None) -> list[np.ndarray]:
    """ORB descriptors of each image (OpenCV ORB, ORB-SLAM's pyramid: 8 levels, scale 1.2)."""
    import cv2  # heavy, and only training needs it: loading a vocabulary (BowIndex, orbslam3) does not

    orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=1.2, nlevels=8)
    out = []
    for i, f in enumerate(files):
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"{f}: not a readable image")
        with baseline_simd():  # the same descriptors on every CPU (octolog.kit.opencv)
            _, desc = orb.detectAndCompute(img, None)
        out.append(np.zeros((0, DESCRIPTOR_BYTES), np.uint8) if desc is None else desc)
        if progress:
            progress(i + 1, len(files))
    return out


@dataclass(frozen=True)
class BuildResult:
    path: Path
    images: int
    descriptors: int
    nodes: int
    words: int


def build(folders: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str], *, k: int = 10, levels: int = 6,
          max_images: int | None = None, n_features: int = 1000, seed: int = 0,
          progress: Callable[[int, int], None] | None = None) -> BuildResult:
    """Images in `folders` → a vocabulary file at `out` (what `octolog vocab build` runs)."""
    _check_params(k, levels, seed)
    if n_features < 1:
        raise InputError(f"features {n_features}: want >= 1 ORB features per image")
    files = list_images(folders, max_images)
    sets = extract(files, n_features=n_features, progress=progress)
    n_desc = sum(s.shape[0] for s in sets)
    if n_desc < k:
        raise InputError(f"{len(files)} images gave only {n_desc} ORB features: too few to train k={k}")
    voc = train(sets, k=k, levels=levels, seed=seed)
    path = voc.save(out)
    return BuildResult(path, len(files), n_desc, voc.n_nodes, voc.n_words)

