"""Rigid bodies: identification from unlabeled 3D points and 6-DoF pose.

Identification uses only geometry: a body's markers have fixed pairwise
distances. For a body we take each marker triangle (a, b, c) as a seed,
find point triples whose three pairwise distances match within a
tolerance, fit the pose of the triple (Kabsch), predict the remaining
markers and collect points within tolerance. Hypotheses are scored by the
number of markers explained, then by the Kabsch RMS. Several bodies are
identified at once by greedy acceptance over all bodies' best hypotheses
with disjoint point sets; a 3-point hypothesis that fits more than one
body equally well is ambiguous and refused (tracking, not identification,
is what continues with 3 of 4 markers).

Poses come from Horn's quaternion method (geometry/alignment.py:
`kabsch_horn` here, its compiled kernel `kabsch_horn_compiled` per tracked
body inside the pipeline's measurement step).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations

import numpy as np

from visionpos.fusion.steps import Steps, finish
from visionpos.geometry.alignment import kabsch_horn

# estimated cost of identification's units of work (ns, the hosts of docs/benchmarks.md), for the size of
# identify_steps' steps (fusion/steps.py): a pair of points tried for a triangle's edge, a placement fitted,
# a candidate placement accepted or refused
PAIR_NS = 6_000
PLACEMENT_NS = 80_000
CANDIDATE_NS = 20_000


@dataclass(frozen=True)
class BodyModel:
    """markers: (M, 3) body-frame marker positions (m)."""

    name: str
    id: int
    markers: np.ndarray

    @property
    def distances(self) -> np.ndarray:
        """(M, M) pairwise marker distances."""
        m = self.markers
        return np.linalg.norm(m[:, None] - m[None], axis=-1)


@dataclass(frozen=True)
class Identification:
    """A body found among points.

    body: index into the model list; point_index: (M,) index of the point
    that is marker m, -1 when the marker was not found; R (3, 3), t (3,)
    body->world pose; rms: Kabsch residual (m).
    """

    body: int
    point_index: np.ndarray
    R: np.ndarray
    t: np.ndarray
    rms: float

    @property
    def n_markers(self) -> int:
        return int((self.point_index >= 0).sum())


def _hypotheses(
    points: np.ndarray, D: np.ndarray, model: BodyModel, tol: float
) -> Steps[list[tuple[int, float, np.ndarray, np.ndarray, np.ndarray]]]:
    """All consistent placements of one body among points (K, 3) m, D (K, K) their distances, in steps of
    one seed triangle each (fusion/steps.py).

    Returns (n_markers, rms, point_index (M,), R, t) tuples.
    """
    mk = model.markers
    M = len(mk)
    Dm = model.distances
    out = []
    seen: set[tuple[int, ...]] = set()
    # seed triangles: every ordered marker triple would repeat work; the
    # unordered triple with point permutations covers all assignments
    for a in range(M):
        for b in range(a + 1, M):
            for c in range(b + 1, M):
                pij = np.argwhere(np.abs(D - Dm[a, b]) < tol)
                fitted = 0
                for i, j in pij:
                    if i == j:
                        continue
                    ks = np.nonzero((np.abs(D[i] - Dm[a, c]) < tol) & (np.abs(D[j] - Dm[b, c]) < tol))[0]
                    for k in ks:
                        if k == i or k == j:
                            continue
                        fitted += 1
                        R, t = kabsch_horn(mk[[a, b, c]], points[[i, j, k]])
                        pred = mk @ R.T + t
                        dist = np.linalg.norm(pred[:, None] - points[None], axis=-1)  # (M, K)
                        idx = np.full(M, -1)
                        idx[[a, b, c]] = [i, j, k]
                        used = {i, j, k}
                        for m in range(M):
                            if idx[m] >= 0:
                                continue
                            order = np.argsort(dist[m])
                            for q in order:
                                if dist[m, q] >= tol:
                                    break
                                if q not in used:
                                    idx[m] = q
                                    used.add(int(q))
                                    break
                        key = tuple(int(v) for v in idx)
                        if key in seen:
                            continue
                        seen.add(key)
                        sel = idx >= 0
                        R, t = kabsch_horn(mk[sel], points[idx[sel]])
                        res = points[idx[sel]] - (mk[sel] @ R.T + t)
                        rms = float(np.sqrt((res**2).sum(axis=1).mean()))
                        if rms < tol:
                            out.append((int(sel.sum()), rms, idx, R, t))
                yield len(pij) * PAIR_NS + fitted * PLACEMENT_NS
    return out


def identify(*args, **kwargs) -> list[Identification]:
    """Find bodies among unlabeled points by their marker geometry: identify_steps (the same arguments) at once."""
    return finish(identify_steps(*args, **kwargs))


def identify_steps(
    points: np.ndarray,
    models: list[BodyModel],
    tolerance: float = 0.008,
    min_markers: int = 3,
    only: list[int] | None = None,
    ambiguous: set[int] | None = None,
) -> Steps[list[Identification]]:
    """Find bodies among unlabeled points by their marker geometry, in steps (fusion/steps.py): a generator
    that yields each step's estimated cost (ns) and returns the result.

    points: (K, 3) world points (m). models: the bodies. tolerance: max
    distance mismatch and Kabsch RMS (m). min_markers: fewest markers for a
    detection (>= 3). only: indices of the models to look for (default all).
    ambiguous: when given, gets the bodies refused because another body fits their points as well.
    Returns at most one Identification per body, with disjoint points. Bodies with the same layout (the
    same markers in the same order) are found as often as they are wanted, in body order: which is which
    is for continuity to say (identity.py), not geometry.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < 3:
        return []
    D = np.linalg.norm(points[:, None] - points[None], axis=-1)
    wanted = list(range(len(models))) if only is None else list(only)
    # bodies that share a layout (the same markers in the same order) share its hypotheses
    layout = [np.asarray(m.markers, np.float64).tobytes() for m in models]
    by_layout: dict[bytes, list] = {}
    cands = []
    for bi in wanted:
        hyps = by_layout.get(layout[bi])
        if hyps is None:
            hyps = by_layout[layout[bi]] = yield from _hypotheses(points, D, models[bi], tolerance)
        for n, rms, idx, R, t in hyps:
            if n >= max(3, min_markers):
                cands.append((n, rms, bi, idx, R, t))
    yield len(cands) * CANDIDATE_NS  # the acceptance below, before it runs
    # more markers first, then smaller residual; deterministic tie-break by body index
    cands.sort(key=lambda c: (-c[0], c[1], c[2]))
    taken: set[int] = set()
    found: dict[int, Identification] = {}
    for n, rms, bi, idx, R, t in cands:
        if bi in found:
            continue
        pts = set(int(v) for v in idx[idx >= 0])
        if pts & taken:
            continue
        # a minimal (3-point) fit that another body explains as well is ambiguous
        if n == 3:
            rivals = [c for c in cands if layout[c[2]] != layout[bi] and c[0] >= 3
                      and set(int(v) for v in c[3][c[3] >= 0]) == pts]
            if rivals:
                if ambiguous is not None:
                    ambiguous.add(bi)
                continue
        found[bi] = Identification(bi, idx, R, t, rms)
        taken |= pts
    return [found[b] for b in sorted(found)]


def layout_ambiguities(models: list[BodyModel], tolerance: float) -> list[str]:
    """Describe marker layouts the identification cannot tell apart (config check).

    Reports bodies whose full layouts match each other and bodies with a
    non-trivial self-symmetry (a marker permutation that is a rigid motion),
    both within `tolerance` (m). Bodies with exactly the same markers in the
    same order are a shared layout, not a problem: continuity tells them apart.
    """
    problems = []
    for i, a in enumerate(models):
        M = len(a.markers)
        if M <= 6:
            for perm in permutations(range(M)):
                if list(perm) == list(range(M)):
                    continue
                R, t = kabsch_horn(a.markers, a.markers[list(perm)])
                res = a.markers[list(perm)] - (a.markers @ R.T + t)
                if np.sqrt((res**2).sum(axis=1).mean()) < tolerance:
                    problems.append(f"body '{a.name}' is symmetric: its orientation is ambiguous")
                    break
        for b in models[i + 1 :]:
            if len(b.markers) != M or np.array_equal(a.markers, b.markers):
                continue  # the very same layout: a fleet, told apart by continuity (identity.py)
            D = np.linalg.norm(b.markers[:, None] - b.markers[None], axis=-1)
            if any(h[0] == M for h in finish(_hypotheses(b.markers, D, a, tolerance))):
                problems.append(f"bodies '{a.name}' and '{b.name}' have the same marker layout: they can be swapped "
                                "(a fleet of identical layouts lists the same markers in the same order)")
    return problems
