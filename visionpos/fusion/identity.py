"""Which body is which, where several bodies share one marker layout (a fleet of identical drones).

A unique layout names its body: identification by geometry (rigidbody.py) is the identity. Bodies
whose layouts are the same (the same markers in the same order: `layout_groups`) cannot be told apart
by geometry; the tracker keeps them apart by continuity (each track's blobs are associated with its own
prediction), and this book says per body how far that identity can be trusted:

  unique layout           its layout names it
  lost                    not tracked
  unresolved: acquired    acquired (or reacquired) by continuity: the nearest lost body of its layout by
                          its last position; a body never seen takes the next name in the parking order
                          (rows along y, each along x: park quad1, quad2, ... in order); until bound
  unresolved: two candidates
                          two tracks of one layout came within the swap distance of each other: their
                          blobs could have changed tracks; both stay unresolved until bound
  tracked-by-continuity   bound (`bind`, by whatever confirms identity: the autopilots' back-channel)
                          and tracked without a break or an ambiguity since

The swap distance of two tracks is the association gate (`fusion.match_gate_px`) in metres at the
farthest camera's range from either (a whole body within that of the other body's prediction could take
its blobs) plus 5 standard deviations of their positions' difference; checked every 5 ms of capture time,
plus how far they close in on each other in 5 ms.
A consumer that sends poses to vehicles sends only to bodies `trusted` says are.
"""

from __future__ import annotations

from enum import Enum

import numpy as np
from scipy.optimize import linear_sum_assignment

from visionpos.fusion.layout import X_POS, X_VEL
from visionpos.fusion.rigidbody import BodyModel, Identification

SWAP_SIGMAS = 5.0  # the swap distance's allowance for the positions' uncertainty
ROW_GAP_M = 0.3  # parking order: bodies whose y differ by less are one row
CHECK_INTERVAL_NS = 5_000_000  # ambiguity checks at most this often (capture clock); the distance grows by
# the two tracks' closing speed times this, so no pair slips through between checks


class IdentityState(str, Enum):
    UNIQUE = "unique layout"
    LOST = "lost"
    ACQUIRED = "unresolved: acquired"
    AMBIGUOUS = "unresolved: two candidates"
    CONTINUITY = "tracked-by-continuity"


def layout_groups(models: list[BodyModel]) -> list[int]:
    """Per model, the index of the first model with exactly the same markers in the same order (itself when
    its layout is unique)."""
    first: dict[bytes, int] = {}
    return [first.setdefault(np.asarray(m.markers, np.float64).tobytes(), i) for i, m in enumerate(models)]


def parking_order(positions: np.ndarray, row_gap_m: float = ROW_GAP_M) -> np.ndarray:
    """Indices that sort points (N, 3) m into rows along y (a gap over row_gap_m in y starts a row), each
    row along x."""
    by_y = np.argsort(positions[:, 1], kind="stable")
    row = np.concatenate([[0], np.cumsum(np.diff(positions[by_y, 1]) > row_gap_m)])
    return by_y[np.lexsort((positions[by_y, 0], row))]


class IdentityBook:
    """Identity state of every body (module docstring).

    camera_centres (V, 3) m world, focal_px (V,) and match_gate_px give the swap distance.
    """

    def __init__(self, models: list[BodyModel], camera_centres: np.ndarray, focal_px: np.ndarray,
                 match_gate_px: float):
        self.names = [m.name for m in models]
        self.group = layout_groups(models)
        members: dict[int, list[int]] = {}
        for b, g in enumerate(self.group):
            members.setdefault(g, []).append(b)
        self.members = {g: bs for g, bs in members.items() if len(bs) > 1}  # shared layouts only
        self.shared = bool(self.members)
        self.state = [IdentityState.UNIQUE if self.group[b] not in self.members else IdentityState.LOST
                      for b in range(len(models))]
        self.detail = [""] * len(models)
        self.last_position = np.full((len(models), 3), np.nan)  # m world, while tracked and after
        self._centres = np.asarray(camera_centres, float).reshape(-1, 3)
        self._shared_bodies = np.array([b for b in range(len(models)) if self.group[b] in self.members], np.int64)
        self._group_of = np.array(self.group, np.int64)
        self._on = np.zeros(len(models), bool)
        self._last_check_ns = -(1 << 62)
        self._gate_rad = float(match_gate_px) / float(np.min(focal_px)) if len(focal_px) else 0.0
        self.swaps_suspected = 0  # ambiguities seen (pairs)

    # ----------------------------------------------------------------- acquisition
    def acquired(self, found: list[Identification], lost: list[int]) -> list[Identification]:
        """Rename the identifications of shared layouts by continuity (the pipeline acquires them under these
        names); found: identify()'s result among the bodies `lost` (the pipeline's untracked ones), each .body
        a lost body of the right layout."""
        if not self.shared or not found:
            return found
        for b in lost:  # the pipeline may have lost it since the last check
            if self.state[b] is not IdentityState.UNIQUE:
                self.state[b] = IdentityState.LOST
        out = [f for f in found if self.group[f.body] not in self.members]
        for g, bodies in self.members.items():
            mine = [f for f in found if self.group[f.body] == g]
            if not mine:
                continue
            candidates = [b for b in bodies if self.state[b] is IdentityState.LOST]
            unseen = {b for b in candidates if np.isnan(self.last_position[b, 0])}
            names = self._continuity_names([f.t for f in mine], candidates)
            new = sum(b in unseen for b in names)
            first = ("first seen: parking order" if new == len(unseen) else
                     f"first seen: parking order of {new} of the {len(unseen)} never seen (the order may be off)")
            for f, b in zip(mine, names):
                out.append(Identification(b, f.point_index, f.R, f.t, f.rms))
                self.state[b] = IdentityState.ACQUIRED
                self.detail[b] = first if b in unseen else "reacquired near its last position"
                self.last_position[b] = f.t
        return sorted(out, key=lambda f: f.body)

    def _continuity_names(self, positions: list[np.ndarray], lost: list[int]) -> list[int]:
        """A lost body for each new track (positions m): the seen ones by the nearest last position
        (Hungarian), the rest in parking order to the never-seen bodies in name order."""
        P = np.array(positions).reshape(-1, 3)
        names = [-1] * len(P)
        seen = [b for b in lost if not np.isnan(self.last_position[b, 0])]
        never = [b for b in lost if np.isnan(self.last_position[b, 0])]
        free = list(range(len(P)))
        if never and len(P) > len(seen):
            # the tracks farthest from every seen body's last position are the new ones
            far = np.array([np.min(np.linalg.norm(self.last_position[seen] - p, axis=1)) if seen else np.inf
                            for p in P])
            new = sorted(np.argsort(-far, kind="stable")[:min(len(never), len(P) - len(seen))].tolist())
            for k, b in zip(np.array(new)[parking_order(P[new])], never):
                names[int(k)] = b
            free = [k for k in free if names[k] < 0]
        if seen and free:
            cost = np.linalg.norm(P[free][:, None] - self.last_position[seen][None], axis=-1)
            rows, cols = linear_sum_assignment(cost)
            for r, c in zip(rows, cols):
                names[free[r]] = seen[c]
        left = [b for b in never if b not in names]
        for k in range(len(P)):
            if names[k] < 0 and left:
                names[k] = left.pop(0)
        return names

    # ------------------------------------------------------------------ tracking
    def after_fusion(self, ref_ns: int, tracked: tuple[int, ...], states: np.ndarray,
                     covariances: np.ndarray) -> None:
        """After a fusion at ref_ns (capture clock; at most every CHECK_INTERVAL_NS): tracked (the pipeline's
        tracked bodies), the filters' states (B, N_STATE) (position m, velocity m/s: layout.X_POS, X_VEL) and
        covariances (B, N_STATE, N_STATE). Marks losses and ambiguous pairs."""
        if 0 <= ref_ns - self._last_check_ns < CHECK_INTERVAL_NS:
            return
        self._last_check_ns = ref_ns
        on = self._on
        on[:] = False
        on[list(tracked)] = True
        sh = self._shared_bodies
        for b in sh[~on[sh]].tolist():
            if self.state[b] is not IdentityState.LOST:
                self.state[b], self.detail[b] = IdentityState.LOST, "track lost"
        live = sh[on[sh]]
        if not len(live):
            return
        x = states[live]
        p = x[:, X_POS]
        self.last_position[live] = p
        if len(live) < 2:
            return
        far = np.sqrt(((p[:, None] - self._centres[None]) ** 2).sum(-1).max(axis=1))  # (L,) m
        var = np.einsum("bii->b", covariances[live][:, X_POS, X_POS])
        v = x[:, X_VEL]
        closing = np.sqrt(((v[:, None] - v[None]) ** 2).sum(-1)) * (CHECK_INTERVAL_NS * 1e-9)
        gate = (self._gate_rad * np.maximum(far[:, None], far[None]) + SWAP_SIGMAS * np.sqrt(var[:, None] + var[None])
                + closing)
        d2 = ((p[:, None] - p[None]) ** 2).sum(-1)
        g = self._group_of[live]
        hit = np.triu((d2 < gate * gate) & (g[:, None] == g[None]), 1)
        if hit.any():
            for a, b in zip(*np.nonzero(hit)):
                self._ambiguous(int(live[a]), int(live[b]))

    def _ambiguous(self, a: int, b: int) -> None:
        if self.state[a] is IdentityState.AMBIGUOUS and self.state[b] is IdentityState.AMBIGUOUS:
            return
        self.swaps_suspected += 1
        for x, y in ((a, b), (b, a)):
            self.state[x] = IdentityState.AMBIGUOUS
            self.detail[x] = f"{self.names[x]} or {self.names[y]}"

    # ------------------------------------------------------------------ binding
    def bind(self, body: int) -> bool:
        """A consumer confirmed the tracked body's identity: tracked-by-continuity from now on (False and no
        change where the body is lost or its layout is unique)."""
        if self.state[body] in (IdentityState.LOST, IdentityState.UNIQUE):
            return False
        self.state[body], self.detail[body] = IdentityState.CONTINUITY, "bound"
        return True

    def trusted(self, body: int) -> bool:
        """Whether the body's identity may be acted on: a unique layout, or bound and continuous since."""
        return self.state[body] in (IdentityState.UNIQUE, IdentityState.CONTINUITY)

    def describe(self, body: int) -> str:
        """One line, e.g. 'quad3: identity unresolved: two candidates (quad3 or quad4)'."""
        s = self.state[body]
        what = f"identity {s.value}" if s is not IdentityState.LOST else "lost"
        return f"{self.names[body]}: {what}" + (f" ({self.detail[body]})" if self.detail[body] else "")

    def states(self) -> tuple[str, ...]:
        """Per body (arena order) its IdentityState's value."""
        return tuple(s.value for s in self.state)
