"""Marching cubes' case table, derived here from the cube's geometry (no copied table).

Corners ``c`` of the unit cube are numbered by their bits ``(x, y, z) = (c & 1, c >> 1 & 1,
c >> 2 & 1)``; the 12 edges join corners that differ in one bit (:data:`EDGES`, 4 along
each axis).  For each of the 256 cases (bit ``c`` set: corner ``c`` is *inside*, its signed
distance below the iso level) every face of the cube pairs the edges where the sign
changes: two such edges are joined; four (the ambiguous face, inside corners on a
diagonal) are joined so that the inside corners stay apart.  That rule reads only the
face's four corners, so two cubes sharing a face cut it the same way and the surface has
no cracks.  Every crossing edge lies on two faces, so the joins close into loops; each
loop is fanned into triangles, turned so that its normal points to the outside.

:data:`TRIS` ``(256, 16)`` int8: per case up to 5 triangles as edge indices, ``-1`` after
the last; :data:`EDGES` ``(12, 2)``: the edge's two corners.
"""

from __future__ import annotations

import numpy as np

CORNERS = np.array([(c & 1, (c >> 1) & 1, (c >> 2) & 1) for c in range(8)], np.int64)


def _edges() -> np.ndarray:
    out = []
    for axis in range(3):
        for c in range(8):
            if not (c >> axis) & 1:
                out.append((c, c | (1 << axis)))
    return np.array(out, np.int64)


EDGES = _edges()
_EDGE_OF = {frozenset(map(int, e)): k for k, e in enumerate(EDGES)}


def _faces() -> list[list[int]]:
    """Each face's 4 corners in cycle order."""
    faces = []
    for axis in range(3):
        a, b = [ax for ax in range(3) if ax != axis]
        for side in (0, 1):
            base = side << axis
            faces.append([base, base | (1 << a), base | (1 << a) | (1 << b), base | (1 << b)])
    return faces


FACES = _faces()


def _loops(case: int) -> list[list[int]]:
    inside = [(case >> c) & 1 == 1 for c in range(8)]
    link: dict[int, list[int]] = {}
    for f in FACES:
        crossing = []  # (edge, its corner that is inside) in cycle order
        for i in range(4):
            p, q = f[i], f[(i + 1) % 4]
            if inside[p] != inside[q]:
                crossing.append(_EDGE_OF[frozenset((p, q))])
        if len(crossing) == 2:
            pairs = [(crossing[0], crossing[1])]
        elif len(crossing) == 4:
            # inside corners apart: pair the two edges around each inside corner
            first_inside = inside[f[1]]  # edges 0 (f0-f1) and 1 (f1-f2) share corner f1
            pairs = ([(crossing[0], crossing[1]), (crossing[2], crossing[3])] if first_inside
                     else [(crossing[1], crossing[2]), (crossing[3], crossing[0])])
        else:
            pairs = []
        for e0, e1 in pairs:
            link.setdefault(e0, []).append(e1)
            link.setdefault(e1, []).append(e0)
    loops, seen = [], set()
    for start in sorted(link):
        if start in seen:
            continue
        loop, prev, cur = [start], None, start
        seen.add(start)
        while True:
            a, b = link[cur]
            nxt = b if a == prev else a
            if nxt == start:
                break
            loop.append(nxt)
            seen.add(nxt)
            prev, cur = cur, nxt
        loops.append(loop)
    return loops


def _oriented(loop: list[int], case: int) -> list[int]:
    """``loop`` turned so that its normal (Newell) points from the inside corners out."""
    mid = np.array([(CORNERS[EDGES[e, 0]] + CORNERS[EDGES[e, 1]]) / 2.0 for e in loop])
    n = np.zeros(3)
    for i in range(len(mid)):
        p, q = mid[i], mid[(i + 1) % len(mid)]
        n += np.cross(p, q)
    out = np.zeros(3)
    for e in loop:
        a, b = EDGES[e]
        inner, outer = (a, b) if (case >> int(a)) & 1 else (b, a)
        out += CORNERS[outer] - CORNERS[inner]
    return loop if float(n @ out) >= 0 else loop[::-1]


def _table() -> np.ndarray:
    tris = -np.ones((256, 16), np.int8)
    for case in range(256):
        k = 0
        for loop in _loops(case):
            loop = _oriented(loop, case)
            for i in range(1, len(loop) - 1):
                tris[case, k:k + 3] = (loop[0], loop[i], loop[i + 1])
                k += 3
    return tris


TRIS = _table()
