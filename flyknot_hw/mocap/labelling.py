"""Unlabelled points -> the 11 rope markers in order, frame by frame.

Algorithm (:func:`label_rope_markers`):

1. **Initialisation from the hanging pose.** A trial starts with the rope at rest, hanging
   straight down from the fingertip: marker k near ``fingertip + s_k g``
   (:func:`flyknot_hw.mocap.stream.hanging_markers`). A rope leaving a tube at an angle hangs
   from a point beside the fingertip (4 cm in the simulated lab), as does one seen through a
   slightly wrong base pose, so the hanging line is first found in the frame: when at least
   ``init_min_markers`` points lie below the fingertip (deeper than half of marker 0's
   arclength, not below the rope's length) within ``init_search_m`` of its vertical, the
   line moves sideways to their median. The first frame where at least
   ``init_min_markers`` of these 11 positions get a point within ``init_gate_m`` (one
   gated assignment, step 3) starts the tracks; markers without a point start lost.
2. **Prediction.** A marker seen in the previous frame ("tracked") is predicted at constant
   velocity (velocity from its last two sightings). A marker lost for at most ``coast_s``
   ("coasting") is extrapolated the same way, its gate growing as
   ``gate_m + accel_m_s2 t^2 / 2`` (t: time since seen; capped at ``reacquire_gate_m``).
   A marker lost for longer ("long lost") is predicted from the rope: on the chord between
   the nearest known rope points on either side (markers matched in this frame, and the
   fingertip when its track is given), interpolated by arclength; straight on along the
   line of the two nearest known points on one side; or carried along with the one known
   point since it was last seen.
3. **Gated assignment in three stages**: tracked, then coasting, then long-lost markers,
   each stage taking the points the stages before it left. A stage solves one
   minimum-cost assignment (Hungarian, ``scipy.optimize.linear_sum_assignment``) of squared
   distances prediction -> point; a pair outside the gate is forbidden, and a marker may stay
   unmatched at the cost of its gate squared. Coasting and long-lost markers must also
   respect the rope (**reach**): within ``|s_i - s_j| + stretch_m`` of the nearest known
   rope point j on each side: the rope between two markers is no longer than its arclength.
   Long-lost markers are matched as many as possible, gated by the reach and (when a known
   rope point is within ``anchor_reach_m`` of reach) ``anchored_gate_m`` around the rough
   prediction, else ``reacquire_gate_m``; and a match is kept only if it is **forced**: in
   every maximum matching of that stage's feasible pairs (when two lost neighbours come back
   in a fold where either could be either, neither is taken until the rope disambiguates).
4. **Ambiguity check.** A match (marker i -> point a) is dropped (marker lost this frame) when
   another point b within the gate of i would cost less than ``ambiguity_m^2`` more: for b
   matched to marker k, the swap cost ``|p_i - b|^2 + |p_k - a|^2 - |p_i - a|^2 - |p_k - b|^2``
   (both markers dropped); for b unmatched, ``|p_i - b|^2 - |p_i - a|^2``. Losing a marker
   for a frame is preferred to giving it a neighbour's label.
5. Points within ``exclude_radius_m`` of the fingertip (track given) are ignored: the marker
   cluster on the hand is not rope.

What it guarantees, per frame:

* The result does not depend on the order of the points within a frame, nor on any label a
  capture program attached to them (labels are discarded: a swap in the lab software's own
  labelling cannot reach the output).
* A tracked marker i (prediction p_i) whose point lies within ``gate_m`` of p_i, with no
  other point within ``gate_m`` of p_i, gets its own point. Sufficient: prediction errors at
  most e <= ``gate_m`` and every other point farther than ``gate_m + e`` from marker i
  (markers sit 0.10 m apart along the rope; the default gate is 0.03 m; e ~ a dt^2 is 6 mm
  at 240 m/s^2 and 200 Hz, 25 mm at the 1000 m/s^2 of a knot's whip end).
* When two points fall within the gates of two tracked markers (neighbours passing close),
  the joint assignment gives each marker its own point if each prediction is nearer its own
  point than the other (sufficient: prediction errors below half the distance between the
  two points), unless the two labellings differ in cost by less than ``ambiguity_m^2``: then
  both markers are lost for that frame. A tracked marker is mislabelled only if its
  prediction is nearer, by that margin, to a wrong point.
* A lost marker is never given a point that would stretch the rope, nor one that another
  feasible labelling of the same frame would give to another marker. It can still take a
  stray (ghost) point that lies within its reach and gate while its own point is missing:
  nothing in one frame tells the two apart. Re-acquisition is not guaranteed when the rope
  folds onto itself (knot formation: the markers crowd, which is also when capture systems
  lose them).

Measured (noise 1 mm, 3 % random dropouts plus gaps of 5-30 frames of two neighbours, two
ghost points a frame, points shuffled): on the five knot-tying motions of ``assets/demos``
(accelerations up to 1000 m/s^2, up to self-contact) all tracked labels were right in 14 of
15 runs and 99.95 % in the last (a ghost taken after the rope vanished).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from flyknot.constants import N_MARKERS
from flyknot.errors import ConfigError, HardwareError, check_int, check_nonnegative, check_positive
from flyknot.geometry import readonly
from flyknot_hw.mocap.stream import hanging_markers, marker_arclengths

__all__ = ["LabelParams", "LabelResult", "label_rope_markers"]

_FORBIDDEN = 1e6  # cost of a pair outside the gate [m^2]; far above any allowed cost
_LOSE_ANCHORED = 1e2  # cost of leaving an anchored lost marker unmatched [m^2]: above any
# allowed pair (so the most markers are matched), below _FORBIDDEN


@dataclass(frozen=True)
class LabelParams:
    """Settings of the labeller (module docstring for their role).

    Attributes:
        gate_m: Gate of a tracked marker around its prediction [m]. Must exceed the
            prediction error (a dt^2 ~ 6 mm at 240 m/s^2, 200 Hz) plus noise, and stay well
            below the marker spacing (0.10 m).
        init_gate_m: Gate around the hanging pose at initialisation [m] (a rope at rest may
            sway by 8 mm at the free end, :class:`flyknot.rest.RestCriterion`).
        init_min_markers: Markers that must be found to initialise.
        init_search_m: Radius about the fingertip's vertical in which the hanging line is
            looked for [m] (0: the rope hangs from the fingertip itself).
        coast_s: How long a lost marker is extrapolated at constant velocity [s].
        accel_m_s2: Acceleration bound that widens a coasting marker's gate [m/s^2].
        reacquire_gate_m: Gate of a lost marker [m] (the cap of the coasting gate).
        stretch_m: Slack of the rope-length constraint on re-acquisition [m] (noise,
            marker size, rope stretch).
        anchor_reach_m: A marker lost for longer than ``coast_s`` whose nearest tracked
            neighbour along the rope is at most this far (as a rope-length reach, e.g.
            0.21 m two markers away) is gated by the rope (reach) and ``anchored_gate_m``
            around its prediction (not ``reacquire_gate_m``) [m].
        anchored_gate_m: Gate of such an anchored lost marker around its rope-shape
            prediction [m] (generous: the prediction is rough; the reach and the forced-match
            rule do the disambiguation).
        ambiguity_m: Margin of the ambiguity check [m] (its square is a cost in m^2).
        exclude_radius_m: Points this close to the fingertip are ignored [m] (only with a
            fingertip track; 0 keeps all).
    """

    gate_m: float = 0.03
    init_gate_m: float = 0.04
    init_min_markers: int = 9
    init_search_m: float = 0.08
    coast_s: float = 0.03
    accel_m_s2: float = 300.0
    reacquire_gate_m: float = 0.05
    stretch_m: float = 0.01
    anchor_reach_m: float = 0.25
    anchored_gate_m: float = 0.1
    ambiguity_m: float = 0.003
    exclude_radius_m: float = 0.03

    def __post_init__(self) -> None:
        for name in ("gate_m", "init_gate_m", "reacquire_gate_m", "anchored_gate_m"):
            check_positive(f"LabelParams.{name}", getattr(self, name))
        nonneg = ("coast_s", "accel_m_s2", "stretch_m", "anchor_reach_m", "ambiguity_m")
        nonneg += ("init_search_m",)
        for name in (*nonneg, "exclude_radius_m"):
            check_nonnegative(f"LabelParams.{name}", getattr(self, name))
        check_int("LabelParams.init_min_markers", self.init_min_markers, 1)
        if self.init_min_markers > N_MARKERS:
            raise ConfigError(
                "LabelParams.init_min_markers",
                f"must be <= {N_MARKERS}, got {self.init_min_markers}",
            )


@dataclass(frozen=True)
class LabelResult:
    """Labelled rope markers and what the labeller saw.

    Attributes:
        markers: Rope markers in order, shape (m, 11, 3) [m]; NaN where lost (and before
            ``init_frame``).
        init_frame: Frame at which the tracks started.
        n_ambiguous: Marker-frames dropped by the ambiguity check.
        n_reacquired: Times a lost marker was picked up again.
    """

    markers: np.ndarray
    init_frame: int
    n_ambiguous: int
    n_reacquired: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "markers", readonly(self.markers))

    @property
    def tracked_fraction(self) -> np.ndarray:
        """Fraction of frames (from ``init_frame``) in which each marker is tracked, (11,)."""
        valid = np.all(np.isfinite(self.markers[self.init_frame :]), axis=2)
        return valid.mean(axis=0) if valid.shape[0] else np.zeros(N_MARKERS)


def _assign(cost: np.ndarray, lose: np.ndarray) -> np.ndarray:
    """Minimum-cost assignment of rows (markers) to columns (points) with an opt-out.

    ``cost`` (r, P) [m^2] (``_FORBIDDEN`` where not allowed), ``lose`` (r,) the cost of
    leaving a row unmatched. Returns the matched column per row, -1 for unmatched.
    """
    r, n_pts = cost.shape
    out = np.full(r, -1)
    if r == 0 or n_pts == 0:
        return out
    dummy = np.full((r, r), _FORBIDDEN)
    dummy[np.arange(r), np.arange(r)] = lose
    rows, cols = linear_sum_assignment(np.hstack([cost, dummy]))
    for i, c in zip(rows, cols, strict=True):
        if c < n_pts and cost[i, c] < _FORBIDDEN:
            out[i] = c
    return out


def _check_inputs(times, points, fingertip):
    t = np.asarray(times, dtype=float)
    pts = np.asarray(points, dtype=float)
    if t.ndim != 1 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ConfigError("times", f"must be finite, increasing, shape (m,), got {t.shape}")
    if pts.ndim != 3 or pts.shape[0] != t.shape[0] or pts.shape[2] != 3:
        raise ConfigError("points", f"must have shape ({t.shape[0]}, P, 3), got {pts.shape}")
    tip = np.asarray(fingertip, dtype=float)
    if tip.shape == (3,):
        if not np.all(np.isfinite(tip)):
            raise ConfigError("fingertip", "must be finite")
        return t, pts, np.broadcast_to(tip, (t.shape[0], 3)), False
    if tip.shape != (t.shape[0], 3):
        raise ConfigError(
            "fingertip", f"must have shape (3,) or ({t.shape[0]}, 3), got {tip.shape}"
        )
    return t, pts, tip, True


def label_rope_markers(
    times: np.ndarray,
    points: np.ndarray,
    fingertip: np.ndarray,
    *,
    params: LabelParams = LabelParams(),
    gravity_dir: np.ndarray = (0.0, 0.0, -1.0),
    arclengths: np.ndarray | None = None,
) -> LabelResult:
    """Label the rope markers of a raw stream (algorithm and guarantees: module docstring).

    Args:
        times: Frame times, shape (m,) [s].
        points: Unlabelled points, shape (m, P, 3) [m], NaN rows for padding.
        fingertip: Fingertip in the mocap frame: shape (3,) [m], its position at rest at the
            start; or shape (m, 3), its track (NaN where unknown), which also enables the
            hand-cluster exclusion and the rope-length constraint of marker 0.
        params: Gates and margins.
        gravity_dir: Direction of gravity in the mocap frame, shape (3,).
        arclengths: Marker arclengths (11,) [m]; None: :func:`marker_arclengths`.

    Returns:
        The labelled markers (m, 11, 3) and counts.

    Raises:
        HardwareError: No frame shows the hanging rope (fewer than ``init_min_markers``
            markers near the hanging pose in every frame).
    """
    t, pts, tip, tip_track = _check_inputs(times, points, fingertip)
    s = marker_arclengths() if arclengths is None else np.asarray(arclengths, dtype=float)
    p = params
    m = t.shape[0]
    out = np.full((m, N_MARKERS, 3), np.nan)

    init, tip0 = _initial_frame(t, pts, tip, tip_track, gravity_dir, s, p, out)

    # Per-marker state: last position (the hanging pose for a marker not found at the
    # start), time seen (-inf: never), frame of that position, velocity.
    found = np.all(np.isfinite(out[init]), axis=1)
    last_x = np.where(found[:, None], out[init], hanging_markers(tip0, gravity_dir, s))
    last_t = np.where(found, t[init], -np.inf)
    last_f = np.full(N_MARKERS, init)
    vel = np.zeros((N_MARKERS, 3))
    n_amb = n_reacq = 0
    for f in range(init + 1, m):
        tip_f = tip[f] if tip_track and np.all(np.isfinite(tip[f])) else None
        obs = _frame_points(pts[f], tip_f, p.exclude_radius_m)
        dt_seen = t[f] - last_t  # inf for never seen
        prev = np.abs(t[f - 1] - last_t) < 1e-12
        coasting = ~prev & (dt_seen <= p.coast_s)
        pred = last_x + vel * np.where(np.isfinite(dt_seen), dt_seen, 0.0)[:, None]
        gate = np.where(prev, p.gate_m, p.reacquire_gate_m)
        grow = p.gate_m + 0.5 * p.accel_m_s2 * np.where(coasting, dt_seen, 0.0) ** 2
        gate = np.where(coasting, np.minimum(grow, p.reacquire_gate_m), gate)
        stages = (np.flatnonzero(prev), np.flatnonzero(coasting), np.flatnonzero(~prev & ~coasting))
        match = _match_stages(obs, stages, pred, gate, last_x, out[last_f], tip_f, s, p)

        amb = _ambiguous(match, pred, gate, obs, p.ambiguity_m)
        n_amb += int(np.count_nonzero(amb))
        match[amb] = -1

        seen = match >= 0
        n_reacq += int(np.count_nonzero(seen & ~prev))
        x_new = obs[np.where(seen, match, 0)] if obs.shape[0] else np.zeros((N_MARKERS, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            v_new = (x_new - last_x) / dt_seen[:, None]
        known = seen & np.isfinite(dt_seen)
        vel = np.where(known[:, None], v_new, np.where(seen[:, None], 0.0, vel))
        last_x = np.where(seen[:, None], x_new, last_x)
        last_t = np.where(seen, t[f], last_t)
        last_f = np.where(seen, f, last_f)
        out[f, seen] = x_new[seen]
    return LabelResult(out, init, n_amb, n_reacq)


def _initial_frame(
    t: np.ndarray,
    pts: np.ndarray,
    tip: np.ndarray,
    tip_track: bool,
    gravity_dir: np.ndarray,
    s: np.ndarray,
    p: LabelParams,
    out: np.ndarray,
) -> tuple[int, np.ndarray]:
    """Step 1 (module docstring): the first frame in which at least ``init_min_markers``
    points lie near the rope hanging from the fingertip; its matched markers are written to
    ``out``. Returns the frame and the hanging line's top there (3,) [m].

    Raises:
        HardwareError: No frame shows the hanging rope.
    """
    for f in range(t.shape[0]):
        tip_f = tip[f] if np.all(np.isfinite(tip[f])) else tip[0]
        if not np.all(np.isfinite(tip_f)):
            continue
        obs = _frame_points(pts[f], tip[f] if tip_track else None, p.exclude_radius_m)
        tip_f = _hanging_line(tip_f, obs, gravity_dir, s, p)
        hang = hanging_markers(tip_f, gravity_dir, s)
        d2 = _sqdist(hang, obs)
        cost = np.where(d2 <= p.init_gate_m**2, d2, _FORBIDDEN)
        match = _assign(cost, np.full(N_MARKERS, p.init_gate_m**2))
        if np.count_nonzero(match >= 0) >= p.init_min_markers:
            out[f, match >= 0] = obs[match[match >= 0]]
            return f, tip_f
    raise HardwareError(
        f"labelling: no frame shows the rope hanging from the fingertip (need "
        f"{p.init_min_markers} of {N_MARKERS} markers within {p.init_gate_m} m of the "
        "hanging pose); check the fingertip position, gravity direction and base pose"
    )


def _match_stages(
    obs: np.ndarray,
    stages: tuple[np.ndarray, np.ndarray, np.ndarray],
    pred: np.ndarray,
    gate: np.ndarray,
    last_x: np.ndarray,
    last_frames: np.ndarray,
    tip_f: np.ndarray | None,
    s: np.ndarray,
    p: LabelParams,
) -> np.ndarray:
    """One frame's matching (module docstring): the markers tracked in the previous frame,
    then the coasting ones, then the long-lost ones, each stage taking the points the stages
    before it left. Returns each marker's point index (11,), -1 unmatched; a long-lost
    marker's prediction in ``pred`` (11, 3) is replaced by the rope's
    (:func:`_rope_prediction`, from the frame it was last seen in, ``last_frames[i]``)."""
    match = np.full(N_MARKERS, -1)
    for stage, idx in enumerate(stages):
        free = np.setdiff1d(np.arange(obs.shape[0]), match[match >= 0])
        if idx.size == 0 or free.size == 0:
            continue
        cur = np.full((N_MARKERS, 3), np.nan)
        cur[match >= 0] = obs[match[match >= 0]]
        if stage == 2:
            for i in idx:
                pred[i] = _rope_prediction(i, pred[i], last_x[i], last_frames[i], cur, tip_f, s)
        d2 = _sqdist(pred[idx], obs[free])
        ok = d2 <= gate[idx, None] ** 2
        lose = gate[idx] ** 2
        if stage > 0:
            reach_ok, reach = _reach(idx, obs[free], cur, tip_f, s, p.stretch_m)
            ok &= reach_ok
            if stage == 2:
                # Anchored close by along the rope: the rope alone gates. The most markers
                # are matched, and a match is kept only if it is forced.
                anchored = reach <= p.anchor_reach_m
                ok[anchored] = reach_ok[anchored] & (d2[anchored] <= p.anchored_gate_m**2)
                lose = np.full(idx.size, _LOSE_ANCHORED)
        sub = _assign(np.where(ok, d2, _FORBIDDEN), lose)
        if stage == 2:
            sub[~_forced(ok, sub)] = -1
        match[idx[sub >= 0]] = free[sub[sub >= 0]]
    return match


def _hanging_line(
    tip: np.ndarray, obs: np.ndarray, gravity_dir: np.ndarray, s: np.ndarray, p: LabelParams
) -> np.ndarray:
    """The top of the line the rope hangs along: ``tip`` moved sideways (across gravity) to
    the median of the points hanging below it (module docstring, step 1), or ``tip``."""
    if p.init_search_m <= 0 or obs.shape[0] < p.init_min_markers:
        return tip
    g = np.asarray(gravity_dir, dtype=float)
    g = g / np.linalg.norm(g)
    rel = obs - tip[None, :]
    depth = rel @ g
    side = rel - depth[:, None] * g[None, :]
    below = (depth > 0.5 * s[0]) & (depth < s[-1] + p.init_gate_m)
    near = below & (np.linalg.norm(side, axis=1) <= p.init_search_m)
    if np.count_nonzero(near) < p.init_min_markers:
        return tip
    return tip + np.median(side[near], axis=0)


def _frame_points(frame: np.ndarray, tip: np.ndarray | None, radius: float) -> np.ndarray:
    """The finite points of a frame (P', 3), without those within ``radius`` of the tip."""
    obs = frame[np.all(np.isfinite(frame), axis=1)]
    if tip is not None and radius > 0 and np.all(np.isfinite(tip)):
        obs = obs[np.linalg.norm(obs - tip, axis=1) > radius]
    return obs


def _sqdist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances between rows of a (r, 3) and b (n, 3), shape (r, n) [m^2]."""
    return np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=2)


def _anchors(i: int, cur: np.ndarray, tip: np.ndarray | None, s: np.ndarray):
    """Nearest known rope points below and above marker i: (arclength [m], position (3,)).

    Known: markers matched so far in this frame (``cur``, NaN where not) and the fingertip
    (arclength 0) when its track is given. Returns two lists ordered away from i (nearest
    first) of at most two anchors each.
    """
    ok = np.all(np.isfinite(cur), axis=1)
    below = [(s[j], cur[j]) for j in range(i - 1, -1, -1) if ok[j]][:2]
    if tip is not None and len(below) < 2:
        below.append((0.0, tip))
    above = [(s[j], cur[j]) for j in range(i + 1, N_MARKERS) if ok[j]][:2]
    return below, above


def _rope_prediction(i, pred_i, x_i, then, cur, tip, s) -> np.ndarray:
    """Prediction (3,) [m] of marker i lost for longer than the coast time (docstring step 2).

    Between known points on both sides: on their chord, interpolated by arclength. On one
    side only: straight on along the line through the two nearest known points. One known
    point only: carried along with it since i was last seen (``x_i``, ``then``: the markers
    in that frame). Nothing known: ``pred_i``.
    """
    below, above = _anchors(i, cur, tip, s)
    if below and above:
        (s0, p0), (s1, p1) = below[0], above[0]
        return p0 + (s[i] - s0) / (s1 - s0) * (p1 - p0)
    side = below or above
    if len(side) == 2:
        (s0, p0), (s1, p1) = side
        d = p0 - p1
        n = np.linalg.norm(d)
        if n > 1e-9:
            return p0 + abs(s[i] - s0) * d / n
    j = next((j for j in _order_from(i) if np.all(np.isfinite(cur[j]))), None)
    if j is not None and np.all(np.isfinite(then[j])) and np.all(np.isfinite(x_i)):
        return x_i + (cur[j] - then[j])
    return pred_i


def _order_from(i: int) -> list[int]:
    """Marker indices by distance along the rope from marker i (i excluded)."""
    return sorted((j for j in range(N_MARKERS) if j != i), key=lambda j: abs(j - i))


def _reach(idx, cand, cur, tip, s, stretch) -> tuple[np.ndarray, np.ndarray]:
    """Candidates that keep the rope within its arclengths, and the tightest reach.

    Returns the mask (len(idx), n) of candidate points within ``|s_i - s_j| + stretch`` of
    the nearest known rope point j on each side of marker i, and per marker the smallest of
    those reaches [m] (inf without any known point).
    """
    ok = np.ones((len(idx), cand.shape[0]), dtype=bool)
    tightest = np.full(len(idx), np.inf)
    for r, i in enumerate(idx):
        below, above = _anchors(i, cur, tip, s)
        for s_j, p_j in below[:1] + above[:1]:
            reach = abs(s[i] - s_j) + stretch
            ok[r] &= np.linalg.norm(cand - p_j, axis=1) <= reach
            tightest[r] = min(tightest[r], reach)
    return ok, tightest


def _max_matching(ok: np.ndarray) -> int:
    """Size of a maximum matching of the bipartite graph ``ok`` (rows x columns, bool)."""
    if ok.size == 0:
        return 0
    rows, cols = linear_sum_assignment(-ok.astype(float))
    return int(np.count_nonzero(ok[rows, cols]))


def _forced(ok: np.ndarray, sub: np.ndarray) -> np.ndarray:
    """Which matches (row r -> column sub[r]) every maximum matching of ``ok`` contains.

    A match is forced iff removing it shrinks the maximum matching; ``sub`` must be a
    maximum matching. Rows without a match are reported False.
    """
    out = np.zeros(sub.shape[0], dtype=bool)
    n = int(np.count_nonzero(sub >= 0))
    for r in np.flatnonzero(sub >= 0):
        cut = ok.copy()
        cut[r, sub[r]] = False
        out[r] = _max_matching(cut) < n
    return out


def _ambiguous(match, pred, gate, obs, margin) -> np.ndarray:
    """Markers whose match is within ``margin`` (as a cost, margin^2) of another choice."""
    amb = np.zeros(N_MARKERS, dtype=bool)
    if margin <= 0 or obs.shape[0] < 2:
        return amb
    owner = np.full(obs.shape[0], -1)
    owner[match[match >= 0]] = np.flatnonzero(match >= 0)
    m2 = margin**2
    for i in np.flatnonzero(match >= 0):
        a = match[i]
        d2 = np.sum((obs - pred[i]) ** 2, axis=1)
        for b in np.flatnonzero(d2 <= gate[i] ** 2):
            if b == a:
                continue
            k = owner[b]
            if k < 0:
                delta = d2[b] - d2[a]
            else:
                dk_a = float(np.sum((obs[a] - pred[k]) ** 2))
                dk_b = float(np.sum((obs[b] - pred[k]) ** 2))
                delta = d2[b] + dk_a - d2[a] - dk_b
            if delta < m2:
                amb[i] = True
                if k >= 0:
                    amb[k] = True
    return amb
