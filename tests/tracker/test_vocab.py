"""Tests of the ORB vocabulary trainer (tracker.vocab) and `octolog vocab build`.

Clustered synthetic descriptors check the tree, the word lookup and the IDF weights exactly;
rendered frames of the synthetic room check the command end to end. ORB-SLAM3 loading and
tracking with a vocabulary built here is in test_orbslam3.py.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from helpers import octolog

from octolog.kit.errors import InputError
from octolog.tracker import vocab


def clustered(n_protos: int, per_image: int, n_images: int, flips: int,
              seed: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Prototype descriptors far apart (~128 bits), and images of noisy copies (`flips` bits each)."""
    rng = np.random.default_rng(seed)
    protos = rng.integers(0, 256, (n_protos, 32), dtype=np.uint8)
    images = []
    for _ in range(n_images):
        which = np.repeat(np.arange(n_protos), per_image)
        d = protos[which].copy()
        bits = np.unpackbits(d, axis=1)
        for row in range(bits.shape[0]):
            bits[row, rng.choice(256, flips, replace=False)] ^= 1
        images.append(np.packbits(bits, axis=1))
    return protos, images


def reference_transform(voc: vocab.Vocabulary, d: np.ndarray) -> int:
    """DBoW2's TemplatedVocabulary::transform, one descriptor, written as plainly as the C++."""
    children: dict[int, list[int]] = {}
    for nid in range(1, voc.parents.shape[0]):
        children.setdefault(int(voc.parents[nid]), []).append(nid)
    node = 0
    while node in children:
        best, best_d = -1, 10**9
        for c in children[node]:
            dist = int(np.unpackbits(np.bitwise_xor(d, voc.descriptors[c])).sum())
            if dist < best_d:
                best, best_d = c, dist
        node = best
    return node


def test_text_round_trip_and_format(tmp_path):
    _, images = clustered(12, 20, 6, 10, seed=1)
    voc = vocab.train(images, k=4, levels=3, seed=7)
    text = voc.to_text()
    lines = text.split("\n")
    assert lines[0] == "4 3  0 0"  # k L, two spaces, scoring L1, weighting TF-IDF (saveToTextFile)
    assert not text.endswith("\n")  # ORB-SLAM3's eof loop would read a bogus node after a newline
    assert len(lines) == voc.n_nodes + 1
    for nid, line in enumerate(lines[1:], start=1):
        parts = line.split(" ")
        assert parts[34] == ""  # FORB::toString's trailing space, then " " weight
        fields = line.split()
        assert len(fields) == 35
        assert 0 <= int(fields[0]) < nid
        assert fields[1] == ("1" if voc.is_leaf[nid] else "0")
        assert all(0 <= int(x) <= 255 for x in fields[2:34])
        if not voc.is_leaf[nid]:
            assert fields[34] == "0"
    back = vocab.parse(text)
    assert back.to_text() == text
    # read from a file line by line, with and without a newline after the last node (ORBvoc.txt has one)
    for ending in ("", "\n"):
        path = tmp_path / f"voc{len(ending)}.txt"
        path.write_text(text + ending, encoding="ascii")
        assert vocab.load(path).to_text() == text
    for a, b in [(back.parents, voc.parents), (back.is_leaf, voc.is_leaf), (back.descriptors, voc.descriptors)]:
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(back.weights, voc.weights, rtol=1e-5)


def test_tree_shape_follows_dbow2():
    _, images = clustered(30, 10, 4, 12, seed=2)
    voc = vocab.train(images, k=5, levels=2, seed=0)
    depth = np.zeros(voc.parents.shape[0], dtype=int)
    for nid in range(1, depth.size):
        depth[nid] = depth[voc.parents[nid]] + 1
    assert depth.max() <= 2
    assert np.bincount(voc.parents[1:]).max() <= 5
    # depth-first creation: all children of a node are consecutive ids
    for p in np.unique(voc.parents[1:]):
        kids = np.flatnonzero(voc.parents == p)
        assert np.array_equal(kids, np.arange(kids[0], kids[0] + kids.size))
    # every descriptor lands on a word: inner nodes never end a descent
    leaves = voc.transform_nodes(np.concatenate(images))
    assert voc.is_leaf[leaves].all()


def test_word_lookup_finds_the_training_cluster():
    protos, images = clustered(8, 25, 5, 8, seed=3)
    voc = vocab.train(images, k=8, levels=1, seed=0)
    assert voc.n_words == 8
    # the 8 well-separated clusters are found: each prototype its own word, and every noisy
    # training copy gets the word of its prototype (the cluster it was drawn from)
    proto_words = voc.transform(protos)
    assert sorted(proto_words.tolist()) == list(range(8))
    for img in images:
        np.testing.assert_array_equal(voc.transform(img), np.repeat(proto_words, 25))
    # a word's centre is the majority of its members: the prototype itself, up to a few bits
    for p, w in zip(protos, proto_words):
        centre = voc.descriptors[voc.word_nodes[w]]
        assert int(np.unpackbits(np.bitwise_xor(p, centre)).sum()) <= 4


def test_vectorised_lookup_matches_dbow2_descent():
    rng = np.random.default_rng(5)
    images = [rng.integers(0, 256, (150, 32), dtype=np.uint8) for _ in range(4)]
    voc = vocab.train(images, k=3, levels=4, seed=11)
    queries = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    got = voc.transform_nodes(queries)
    want = [reference_transform(voc, q) for q in queries]
    assert got.tolist() == want


def test_idf_weights():
    # 4 images; prototype 0 in all of them, prototype 1 in half: IDF ln(4/4) = 0 and ln(4/2)
    protos, _ = clustered(2, 1, 1, 0, seed=4)
    noise = np.random.default_rng(0)

    def copies(p: np.ndarray, n: int) -> np.ndarray:
        bits = np.repeat(np.unpackbits(p)[None], n, axis=0)
        for row in bits:
            row[noise.choice(256, 6, replace=False)] ^= 1
        return np.packbits(bits, axis=1)

    images = [np.concatenate([copies(protos[0], 10), copies(protos[1], 10)]) if i % 2 else copies(protos[0], 20)
              for i in range(4)]
    voc = vocab.train(images, k=2, levels=1, seed=0)
    w = voc.transform(protos)
    assert voc.weights[voc.word_nodes[w[0]]] == pytest.approx(0.0)
    assert voc.weights[voc.word_nodes[w[1]]] == pytest.approx(math.log(2.0))


def test_training_is_deterministic_and_seeded():
    rng = np.random.default_rng(6)
    images = [rng.integers(0, 256, (300, 32), dtype=np.uint8) for _ in range(3)]
    a = vocab.train(images, k=6, levels=3, seed=1).to_text()
    assert vocab.train(images, k=6, levels=3, seed=1).to_text() == a
    assert vocab.train(images, k=6, levels=3, seed=2).to_text() != a


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory):
    """A few frames of the synthetic room as PNG files (no ../shared needed)."""
    from octolog.replay.synthetic import SyntheticScene

    folder = tmp_path_factory.mktemp("images")
    scene = SyntheticScene(n_frames=60)
    for i in range(0, 60, 12):
        cv2.imwrite(str(folder / f"{i:04d}.png"), cv2.cvtColor(scene.render(i).rgb, cv2.COLOR_RGB2BGR))
    return folder


def test_build_command_is_byte_identical_run_to_run(image_dir, tmp_path):
    args = [str(image_dir), "--k", "5", "--levels", "3", "--features", "500", "--seed", "3", "--quiet"]
    out = octolog("vocab", "build", *args, "--out", str(tmp_path / "a.txt")).stdout
    assert "5 images" in out and "a.txt" in out
    octolog("vocab", "build", *args, "--out", str(tmp_path / "b.txt"))
    a, b = (tmp_path / "a.txt").read_bytes(), (tmp_path / "b.txt").read_bytes()
    assert a == b
    voc = vocab.load(tmp_path / "a.txt")
    assert (voc.k, voc.levels) == (5, 3) and 25 <= voc.n_words <= 125
    assert voc.weights[voc.is_leaf].max() > 0  # some words are rarer than others
    # an existing file is not replaced silently
    proc = octolog("vocab", "build", *args, "--out", str(tmp_path / "a.txt"), check=False)
    assert proc.returncode == 1 and "--overwrite" in proc.stderr


def one_line_error(proc) -> str:
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("octolog vocab: error: "), proc.stderr
    assert "Traceback" not in proc.stderr
    return lines[0]


def test_bad_image_folders_are_one_line_errors(tmp_path):
    out = str(tmp_path / "voc.txt")
    assert "not a folder" in one_line_error(octolog("vocab", "build", str(tmp_path / "nope"), "--out", out,
                                                    check=False))
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no images here")
    assert "no images" in one_line_error(octolog("vocab", "build", str(empty), "--out", out, check=False))
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "0001.png").write_bytes(b"not a png")
    assert "0001.png" in one_line_error(octolog("vocab", "build", str(broken), "--out", out, check=False))
    assert not (tmp_path / "voc.txt").exists()


def test_bad_parameters_and_files_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="k=30"):
        vocab.train([np.zeros((50, 32), np.uint8)], k=30)
    with pytest.raises(InputError, match="levels=0"):
        vocab.train([np.zeros((50, 32), np.uint8)], levels=0)
    bad = tmp_path / "bad.txt"
    bad.write_text("10 6  0 0\n0 0 1 2 3\n")
    with pytest.raises(InputError, match="line 2"):
        vocab.load(bad)
    hello = tmp_path / "hello.txt"
    hello.write_text("hello\n")
    with pytest.raises(InputError, match="not a DBoW2"):
        vocab.check_header(hello)
    # ORB-SLAM3 loads a truncated file without complaint: the cheap check looks at the end too
    rng = np.random.default_rng(0)
    good = vocab.train([rng.integers(0, 256, (200, 32), dtype=np.uint8)], k=4, levels=2).save(tmp_path / "v.txt")
    vocab.check_header(good)
    cut = tmp_path / "cut.txt"
    cut.write_bytes(good.read_bytes()[:-30])
    with pytest.raises(InputError, match="truncated"):
        vocab.check_header(cut)
