"""The pruned octree of OctoMap's `.bt`/`.ot` files, built from full-resolution voxels (vectorised, level by level)."""

from __future__ import annotations

import numpy as np

from octolog.mapper.octokeys import TREE_DEPTH

__all__ = ["WHITE", "Tree", "build_tree"]

WHITE = 255  # (255, 255, 255): "no colour", as in OctoMap


def _spread3(v: np.ndarray) -> np.ndarray:
    """Spread the 16 low bits of v to every third bit (Morton interleave helper), uint64."""
    x = v.astype(np.uint64) & np.uint64(0xFFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x0C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x249249249249)
    return x


def _morton(keys: np.ndarray) -> np.ndarray:
    """Depth-first order code: at every level the child index is x_bit + 2 y_bit + 4 z_bit."""
    return _spread3(keys[:, 0]) | (_spread3(keys[:, 1]) << np.uint64(1)) | (_spread3(keys[:, 2]) << np.uint64(2))


class Tree:
    """A pruned octree in depth-first (pre-)order: one row per node."""

    def __init__(self, n: int, with_rgb: bool) -> None:
        self.size = n
        self.leaf = np.zeros(n, dtype=bool)
        self.value = np.zeros(n, dtype=np.float32)
        self.child_mask = np.zeros(n, dtype=np.uint8)
        self.bt_bits = np.zeros(n, dtype=np.int64)
        self.rgb = np.zeros((n, 3), dtype=np.uint8) if with_rgb else None


def build_tree(keys: np.ndarray, prune_key: np.ndarray, value: np.ndarray, occupied: np.ndarray,
                rgb: np.ndarray | None) -> Tree:
    """Bottom-up octree over full-resolution voxels, pruned where 8 leaf siblings share `prune_key`.

    Inner values are the max of the children (OctoMap's updateOccupancyChildren); inner colours
    the truncated mean of the children's set colours, white if none (getAverageChildColor).
    The root (depth 0) is never pruned, as in OctoMap's `prune()`.
    """
    n = keys.shape[0]
    if n == 0:
        return Tree(0, rgb is not None)
    code = _morton(keys).astype(np.int64)
    order = np.argsort(code, kind="stable")
    code = code[order]
    pk = prune_key[order]
    val = value[order].astype(np.float32)
    col = rgb[order].astype(np.int64) if rgb is not None else None
    leaf = np.ones(n, dtype=bool)
    occ = occupied[order]  # leaf state, for the .bt bits
    cmask = np.zeros(n, dtype=np.int64)
    bits = np.zeros(n, dtype=np.int64)

    parts: list[tuple] = []
    state = (code, pk, val, col, leaf, occ, cmask, bits)
    for level in range(1, TREE_DEPTH + 1):
        part, state = _level_up(level, state)
        parts.append(part)
    code, pk, val, col, leaf, occ, cmask, bits = state
    parts.append((code, TREE_DEPTH, leaf, val, cmask, bits, col))
    return _preorder(parts, rgb is not None)


def _level_up(level: int, state: tuple) -> tuple[tuple, tuple]:
    """One level up: the nodes kept at `level - 1` and the parents' (code, pk, val, col, leaf, occ, cmask, bits)."""
    code, pk, val, col, leaf, occ, cmask, bits = state
    parent = code >> 3
    pos = code & 7
    starts = np.flatnonzero(np.concatenate(([True], parent[1:] != parent[:-1])))
    counts = np.diff(np.append(starts, parent.shape[0]))
    gid = np.repeat(np.arange(starts.shape[0]), counts)
    all_leaf = np.logical_and.reduceat(leaf, starts)
    same = np.minimum.reduceat(pk, starts) == np.maximum.reduceat(pk, starts)
    collapse = (counts == 8) & all_leaf & same & (level < TREE_DEPTH)
    # children's .bt codes: 01 occupied leaf, 10 free leaf, 11 inner (bit 2i is "free").
    child_code = np.where(leaf, np.where(occ, 2, 1), 3) << (2 * pos)
    p_bits = np.bitwise_or.reduceat(child_code, starts)
    p_mask = np.bitwise_or.reduceat(np.int64(1) << pos, starts)
    p_val = np.maximum.reduceat(val, starts)
    p_col = None
    if col is not None:
        is_set = np.any(col != WHITE, axis=1)
        n_set = np.add.reduceat(is_set.astype(np.int64), starts)
        sums = np.add.reduceat(col * is_set[:, None], starts, axis=0)
        p_col = np.where(n_set[:, None] > 0, sums // np.maximum(n_set, 1)[:, None], WHITE)
    keep = ~collapse[gid]
    part = (code[keep], level - 1, leaf[keep], val[keep], cmask[keep], bits[keep],
            col[keep] if col is not None else None)
    # Next level: collapsed groups become leaves with their children's data.
    first = starts
    code = parent[starts]
    leaf = collapse
    pk = np.where(collapse, pk[first], np.int64(-1))
    occ = np.where(collapse, occ[first], False)
    val = np.where(collapse, val[first], p_val).astype(np.float32)
    cmask = np.where(collapse, 0, p_mask)
    bits = np.where(collapse, 0, p_bits)
    if col is not None:
        col = np.where(collapse[:, None], col[first], p_col)
    return part, (code, pk, val, col, leaf, occ, cmask, bits)


def _preorder(parts: list[tuple], with_rgb: bool) -> Tree:
    """Every level's kept nodes in one depth-first (pre-order) table."""
    all_code = np.concatenate([p[0] << (3 * p[1]) for p in parts])
    all_level = np.concatenate([np.full(p[0].shape[0], p[1], np.int64) for p in parts])
    # Pre-order: by prefix code, parents (higher level) before their first descendant.
    order = np.lexsort((-all_level, all_code))
    tree = Tree(all_code.shape[0], with_rgb)
    tree.leaf = np.concatenate([p[2] for p in parts])[order]
    tree.value = np.concatenate([p[3] for p in parts])[order]
    tree.child_mask = np.concatenate([p[4] for p in parts])[order].astype(np.uint8)
    tree.bt_bits = np.concatenate([p[5] for p in parts])[order]
    if with_rgb:
        tree.rgb = np.concatenate([p[6] for p in parts])[order].astype(np.uint8)
    return tree
