"""Rest after motion: the held end thrown as in a flying knot, then held still; after the wait
the rope's shape is compared with the shape it takes when lowered gently.

The case (:func:`rest_after_motion`) and its measures, each a pure function of vertices:
:func:`flyknot.geometry.turning_angles` (the angle between consecutive segments),
:func:`couple_hold_angles`
(the largest zig-zag a rope's frictional bending couple holds still under the hanging
tension), :func:`kinks` (the turning angles beyond the gently lowered shape and that hold) and
:func:`shape_offset` (the distance to the gently lowered shape with the swing turned out). The
picture: :func:`draw_rest_after_motion`.
"""

from __future__ import annotations

import functools
import textwrap
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from flyknot.errors import check_positive
from flyknot.geometry import min_rotation, turning_angles
from flyknot.rest import RestCriterion
from flyknot.verdict import UNKNOTTED, judge_centreline
from flyknot_sim.bend_friction import joint_moments
from flyknot_sim.rope_handle import hanging_vertices
from flyknot_sim.rope_table import RopeParams
from flyknot_tools.rope_study.harness import HOLDER_JOINTS, HandMotion, holder_targets
from flyknot_tools.rope_validate.bench import Bench, RopeModel
from flyknot_tools.rope_validate.common import DOWN, HOME, CaseResult, G, hung, result

__all__ = [
    "KINK_DEG",
    "Kinks",
    "Throw",
    "couple_hold_angles",
    "draw_rest_after_motion",
    "gently_lowered",
    "hanging_at_home",
    "hanging_tensions",
    "kinks",
    "rest_after_motion",
    "shape_offset",
    "turned_to_swing",
]

KINK_DEG = 5.0
"""Largest median turning angle of a rope at rest beyond its gently lowered shape [deg]."""
BIG_KINK_DEG = 30.0
"""Turning angle [deg] from which a joint is counted as a kink in the report."""
TRACE_EVERY_S = 0.01
"""Sampling interval of the wait [s]."""


# ----------------------------------------------------------------------------------------
# the held end's motion
# ----------------------------------------------------------------------------------------
@functools.cache
def _flying_knot_motion() -> HandMotion:
    return HandMotion.load()


@dataclass(frozen=True)
class Throw:
    """The held end's motion: the rope study's flying-knot hand motion (it tied a flying knot
    in rope 1 in the feasibility study: the hand up to 0.48 m up and 0.37 m and 0.33 m across,
    turned over, peak speed 3.87 m/s, 0.76 s), played ``speed`` times as fast from where the holder
    is, then held still at its last pose.

    Attributes:
        speed: Time scale [-] (1: as recorded; 1.2: 20 % faster, peak 4.6 m/s).
        turn: Play the hand's rotations too (False: the tube keeps pointing down).
    """

    speed: float = 1.0
    turn: bool = True

    def __post_init__(self) -> None:
        check_positive("speed", self.speed)

    @property
    def motion(self) -> HandMotion:
        """The hand motion at this speed."""
        m = _flying_knot_motion()
        return HandMotion(m.t / self.speed, m.pos, m.quat)

    @property
    def duration(self) -> float:
        """The motion's length [s]."""
        return self.motion.duration

    @property
    def peak_speed(self) -> float:
        """The hand's peak speed [m/s]."""
        m = self.motion
        return float(np.linalg.norm(np.gradient(m.pos, m.t, axis=0), axis=1).max())

    def targets(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Holder joint targets q (k, 6) [m, rad] and rates (k, 6) at the steps 0, dt, ...
        through the motion's end (slides from the motion's start; hinges b, a, c)."""
        m = self.motion
        t = np.arange(round(m.duration / dt) + 1) * dt
        q, qd = holder_targets(m, t, m.pos[0])
        if not self.turn:
            q[:, 3:], qd[:, 3:] = 0.0, 0.0
        return q, qd

    def path(self, dt: float) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
        """The holder path (:data:`~flyknot_tools.rope_validate.bench.HolderPath`): the
        motion, then its last pose held still."""
        q, qd = self.targets(dt)
        still = np.zeros(6)

        def at(t: float) -> tuple[np.ndarray, np.ndarray]:
            i = round(t / dt)
            return (q[i], qd[i]) if i < len(q) else (q[-1], still)

        return at

    def label(self) -> str:
        """The motion in words."""
        turned = "hand turned" if self.turn else "tube kept down"
        return f"flying-knot throw x{self.speed:g} (peak {self.peak_speed:.1f} m/s, {turned})"


# ----------------------------------------------------------------------------------------
# measures
# ----------------------------------------------------------------------------------------
def hanging_tensions(p: RopeParams) -> np.ndarray:
    """Tension [N] of the rope hanging at rest in the segment below each interior vertex
    k = 1..n-1: the weight of the vertices below it, T_k = g (m_end + rho l (n - k - 1/2))
    (the rope's mass lumped on its vertices, half a segment's at the free end); shape (n - 1,)."""
    k = np.arange(1, p.segments)
    return G * (p.end_mass + p.density * p.segment_length * (p.segments - k - 0.5))


def couple_hold_angles(p: RopeParams) -> np.ndarray:
    """The largest turning angle [rad] of a zig-zag that the rope's frictional couple M_0
    holds still at each interior vertex k = 1..n-1 of the hanging rope; shape (n - 1,).

    In a zig-zag of turning angle theta (alternating sides) under tension T_k
    (:func:`hanging_tensions`) the tension pushes each joint straight with the force T_k theta,
    and the elastic moment B theta / l does too; the joints' couples, alternating in sign,
    push back with at most 4 M_0 / l. Still where 4 (M_0 - B theta / l) / l >= T_k theta:
    theta <= 4 M_0 / (T_k l + 4 B / l). With the links' friction (``link_friction_radius``)
    M_0 is each joint's M_0 + mu r T (:func:`flyknot_sim.bend_friction.joint_moments`, the
    joint's tension at rest). Zero without a couple (the chain, the latex tube)."""
    tension = hanging_tensions(p)
    edges = np.r_[tension[0], tension]  # edge 0, held, is not read (joint_tensions)
    m0 = joint_moments(p.frictional_couple, p.link_friction_arm, edges, p.segments)
    if m0.max() <= 0:
        return np.zeros(p.segments - 1)
    seg = p.segment_length
    return 4 * m0 / (tension * seg + 4 * p.bending_stiffness / seg)


@dataclass(frozen=True)
class Kinks:
    """The turning angles of a rope's free joints (vertices 2..n-1; the joint at the held
    segment turns with the swing) [deg].

    Attributes:
        median_excess_deg: Median over the joints of the turning angle beyond the gently
            lowered rope's at that joint and the zig-zag the rope's couple holds there.
        max_excess_deg: The largest such excess.
        median_turn_deg: Median turning angle.
        max_turn_deg: Largest turning angle.
        over_30: Joints turning by more than :data:`BIG_KINK_DEG`.
    """

    median_excess_deg: float
    max_excess_deg: float
    median_turn_deg: float
    max_turn_deg: float
    over_30: int


def kinks(x: np.ndarray, x_ref: np.ndarray, hold: np.ndarray) -> Kinks:
    """The :class:`Kinks` of vertices x (n + 1, 3) against the gently lowered x_ref
    (n + 1, 3) and the couple's hold angles ``hold`` (n - 1,) [rad] (:func:`couple_hold_angles`)."""
    turn = np.degrees(turning_angles(x))[1:]
    excess = turn - np.degrees(turning_angles(x_ref))[1:] - np.degrees(np.asarray(hold))[1:]
    return Kinks(
        float(np.median(excess)),
        float(excess.max()),
        float(np.median(turn)),
        float(turn.max()),
        int(np.sum(turn > BIG_KINK_DEG)),
    )


def turned_to_swing(x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """x_ref (n + 1, 3) with its vertices 2..n turned about vertex 1 by the smallest rotation
    that points its chord (vertex 1 to the free end) along that of x (n + 1, 3): the gently
    lowered shape swung as x is swung about the hold."""
    x, x_ref = np.asarray(x, dtype=float), np.asarray(x_ref, dtype=float)
    r = min_rotation(x_ref[-1] - x_ref[1], x[-1] - x[1])
    turned = (x_ref - x_ref[1]) @ r.T + x_ref[1]
    turned[:2] = x_ref[:2]  # the held segment does not swing
    return turned


def shape_offset(x: np.ndarray, x_ref: np.ndarray) -> float:
    """Largest distance [m] of a vertex of x (n + 1, 3) from the gently lowered x_ref
    (n + 1, 3) swung as x is (:func:`turned_to_swing`): the shape's difference, the swing
    about the hold turned out."""
    return float(np.linalg.norm(np.asarray(x) - turned_to_swing(x, x_ref), axis=1).max())


# ----------------------------------------------------------------------------------------
# the case
# ----------------------------------------------------------------------------------------
@dataclass
class _Wait:
    """What is sampled over the wait: times [s], vertices (n + 1, 3) [m], free-end speeds
    [m/s]."""

    t: list = field(default_factory=list)
    x: list = field(default_factory=list)
    end_speed: list = field(default_factory=list)

    def add(self, bench: Bench) -> None:
        v = bench.harness.rope.vertex_velocities(bench.model, bench.data)
        self.t.append(bench.t)
        self.x.append(bench.vertices())
        self.end_speed.append(float(np.linalg.norm(v[-1])))

    def end_speed_over(self, seconds: float) -> float:
        """The free end's largest speed over the last ``seconds`` [m/s]."""
        t = np.asarray(self.t)
        return float(np.max(np.asarray(self.end_speed)[t >= t[-1] - seconds + 1e-9]))


def hanging_at_home(p: RopeParams) -> np.ndarray:
    """The rope hanging straight down from the holder at :data:`HOME`."""
    x0 = HOME + DOWN * p.clearance
    return hanging_vertices(x0, x0 + DOWN * p.segment_length, DOWN, p.segments)


def gently_lowered(rope: RopeModel, hold: np.ndarray, seconds: float) -> np.ndarray:
    """The rope's vertices (n + 1, 3) when lowered gently from the holder posed at joint
    targets ``hold`` (6,): the held segment where the hold puts it, the rest started straight
    down from it at rest, settled for ``seconds``."""
    p = rope.params
    b = hung(rope, hanging_at_home(p))
    m, d = b.model, b.data
    for name, q in zip(HOLDER_JOINTS, hold, strict=True):
        d.qpos[m.joint(name).qposadr[0]] = q
    sites = b.harness.rope.hold_sites
    mujoco.mj_kinematics(m, d)
    held = d.site_xpos[sites].copy()
    b.place(hanging_vertices(held[0], held[1], DOWN, p.segments))
    still = np.zeros(6)
    b.run(seconds, lambda _t: (hold, still))
    return b.vertices()


def rest_after_motion(
    rope: RopeModel,
    throw: Throw = Throw(),
    wait_s: float = 10.0,
    reference_s: float = 3.0,
    picture: str | Path | None = None,
) -> CaseResult:
    """The holder throws the rope (``throw``: the flying-knot hand motion), holds still for
    ``wait_s``, and the rope's shape is compared with the shape it takes when lowered gently
    (:func:`gently_lowered`: hung from the holder in its last pose, started straight down at
    rest, settled ``reference_s``): a chain hangs straight below the held segment, a cord and a
    tube with the bend their stiffness and end weight give.

    Expected: no kinks after the wait. The median over the free joints (vertices 2..n-1) of
    the turning angle beyond the gently lowered rope's and beyond the zig-zag the rope's
    frictional couple holds still (:func:`couple_hold_angles`; none for the chain and the
    tube) is at most 5 deg (:data:`KINK_DEG`). Why: a hanging rope's tension pushes every
    joint straight (T theta at a joint turned by theta), and only a bending couple holds a
    joint bent against it; a kink that moves is a wave that the rope's internal friction
    stops (a chain's links rub steel on steel, mu 0.57; a cord's fibres slide). 5 deg: the
    project's line for "no kinks" (the chain's median turning angle 10 s after the motion),
    inside what the lab's rest criterion already tolerates (a zig-zag of theta at every joint
    lifts the free end by L theta^2 / 8: 1 mm at 5 deg; the criterion's 8.4 mm at 14 deg). A
    rope that still swings as a pendulum bends little at its joints (ropes 1-5 and 7, their
    free ends still at 0.6-1.4 m/s 10 s after the throw, measure medians of 0.4-1.3 deg).

    Reported, not judged: the largest turning angle and the joints over 30 deg; the largest
    distance from the gently lowered shape with the swing turned out (:func:`shape_offset`)
    and the free end's offset from its gently lowered position; the free end's largest speed
    over the last second beside the lab's rest criterion (0.03 m/s,
    :class:`flyknot.rest.RestCriterion`). The speed is not judged: a thrown rope swings on as
    a pendulum, which air drag alone takes down slowly (amplitude ~ 1 / cycles: a 0.4 m swing
    of the free end keeps 0.23-0.37 m after 5 cycles, ~10 s, on ropes 1-7,
    :func:`~flyknot_tools.rope_validate.cases.drag_decay_theory`), and no rope's internal
    damping of a swing is published (``assets/ropes.toml``). A rope the throw knotted has
    another rest shape: its result is reported, not judged.

    ``picture``: where to write a PNG of the two shapes and of the wait
    (:func:`draw_rest_after_motion`); None: none.
    """
    p = rope.params
    b = hung(rope, hanging_at_home(p))
    path = throw.path(b.dt)
    b.run(throw.duration, path)
    wait = _Wait()
    b.run(wait_s, path, TRACE_EVERY_S, wait.add)
    x = b.vertices()
    x_ref = gently_lowered(rope, path(b.t)[0], reference_s)
    hold = couple_hold_angles(p)
    measured = {"throw": throw.label(), "wait_s": wait_s, **_measures(x, x_ref, hold, wait)}
    out = result(
        "rest_after_motion",
        rope,
        measured["median_excess_deg"] <= KINK_DEG,
        f"no kinks {wait_s:g} s after a throw: median turning angle within {KINK_DEG:g} deg of "
        "the gently lowered rope's (plus the zig-zag its frictional couple holds)",
        "a hanging rope's tension straightens every joint that no bending couple holds; "
        "internal friction stops a moving kink (links rub, fibres slide); 5 deg: the "
        "project's line for no kinks",
        measured,
        _detail(measured),
        applies=measured["final"] == UNKNOTTED,
    )
    if picture is not None:
        draw_rest_after_motion(picture, x, x_ref, wait, hold, out)
        out.measured["picture"] = str(picture)
    return out


def _measures(x: np.ndarray, x_ref: np.ndarray, hold: np.ndarray, wait: _Wait) -> dict:
    """The case's numbers: the kinks of x against x_ref and ``hold``, the shape's offsets,
    the free end's speed over the rest criterion's window, the rope's topology."""
    k = kinks(x, x_ref, hold)
    rest = RestCriterion()
    return {
        "median_excess_deg": k.median_excess_deg,
        "max_excess_deg": k.max_excess_deg,
        "median_turn_deg": k.median_turn_deg,
        "max_turn_deg": k.max_turn_deg,
        "joints_over_30_deg": k.over_30,
        "lowered_median_turn_deg": float(np.degrees(np.median(turning_angles(x_ref)[1:]))),
        "couple_holds_deg": [float(np.degrees(hold[1:].min())), float(np.degrees(hold.max()))],
        "shape_offset_m": shape_offset(x, x_ref),
        "end_offset_m": float(np.linalg.norm(x[-1] - x_ref[-1])),
        "end_speed_m_s": wait.end_speed_over(rest.window_s),
        "rest_speed_m_s": rest.speed_m_s,
        "final": judge_centreline(x).klass,
    }


def _detail(m: dict) -> str:
    """The result's line: the kinks, the shape, the free end."""
    holds = m["couple_holds_deg"]
    couple = f", couple holds {holds[0]:.0f}-{holds[1]:.0f} deg" if holds[1] > 0 else ""
    knot = "" if m["final"] == UNKNOTTED else f"; {m['final']}: reported"
    return (
        f"{m['wait_s']:g} s after the throw: median turning {m['median_turn_deg']:.1f} deg "
        f"(lowered gently {m['lowered_median_turn_deg']:.1f}{couple}; excess "
        f"{m['median_excess_deg']:+.1f}), max {m['max_turn_deg']:.0f} deg (excess "
        f"{m['max_excess_deg']:+.0f}), {m['joints_over_30_deg']} over 30 deg; shape off "
        f"{m['shape_offset_m'] * 1e3:.0f} mm "
        f"without the swing, free end {m['end_offset_m'] * 1e3:.0f} mm off, "
        f"{m['end_speed_m_s']:.2f} m/s (rest <= {m['rest_speed_m_s']:g}){knot}"
    )


# ----------------------------------------------------------------------------------------
# the picture
# ----------------------------------------------------------------------------------------
def draw_rest_after_motion(
    path: str | Path,
    x: np.ndarray,
    x_ref: np.ndarray,
    wait: _Wait,
    hold: np.ndarray,
    res: CaseResult,
) -> Path:
    """A PNG at ``path``: the rope after the wait and lowered gently (also swung as the rope
    is), seen along y and along x; the turning angle at every joint; and over the wait the
    median turning angle beyond the gently lowered shape and the couple's hold [deg] and the
    free end's speed [m/s]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        1, 4, figsize=(17, 5.2), gridspec_kw={"width_ratios": [1, 1, 1.3, 1.6]}
    )
    _draw_shapes(axes[:2], x, x_ref)
    _draw_joints(axes[2], x, x_ref, hold)
    _draw_wait(axes[3], wait, x_ref, hold, res.measured["rest_speed_m_s"])
    verdict = ("pass" if res.passed else "FAIL") if res.applies else "reported"
    head = f"rest after motion, rope {res.rope} ({res.variant}): {verdict}"
    fig.suptitle(head + "\n" + "\n".join(textwrap.wrap(res.detail, 150)), fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _draw_shapes(axes, x: np.ndarray, x_ref: np.ndarray) -> None:
    """The two shapes seen along y and along x."""
    turned = turned_to_swing(x, x_ref)
    for ax, (i, name) in zip(axes, ((0, "x"), (1, "y")), strict=True):
        ax.plot(x_ref[:, i], x_ref[:, 2], "--", color="0.6", label="lowered gently")
        ax.plot(turned[:, i], turned[:, 2], ":", color="0.2", label="the same, swung as the rope")
        ax.plot(x[:, i], x[:, 2], "o-", ms=3, color="C1", label="after the wait")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{name} [m]")
        ax.set_ylabel("z [m]")
    axes[0].legend(fontsize=8, loc="lower left")


def _draw_joints(ax, x: np.ndarray, x_ref: np.ndarray, hold: np.ndarray) -> None:
    """The turning angle at every joint after the wait, lowered gently, and with the hold."""
    k = np.arange(1, len(x) - 1)
    ref = np.degrees(turning_angles(x_ref))
    ax.plot(k, np.degrees(turning_angles(x)), "o-", ms=3, color="C1", label="after the wait")
    ax.plot(k, ref, "--", color="0.6", label="lowered gently")
    if hold.max() > 0:
        ax.plot(k, ref + np.degrees(hold), ":", color="0.2", label="+ the couple's hold")
    ax.axhline(BIG_KINK_DEG, color="0.8", lw=0.8)
    ax.set_ylim(0, 90)
    ax.set_xlabel("joint (vertex; 1: at the held segment)")
    ax.set_ylabel("turning angle [deg]")
    ax.legend(fontsize=8, loc="upper left")


def _draw_wait(ax, wait: _Wait, x_ref: np.ndarray, hold: np.ndarray, rest: float) -> None:
    """Over the wait: the median turning beyond the gently lowered shape and the hold [deg]
    with the pass line, and the free end's speed [m/s] with the lab's rest speed."""
    excess = [kinks(xi, x_ref, hold).median_excess_deg for xi in wait.x]
    ax.plot(wait.t, excess, color="C0", lw=0.8)
    ax.axhline(KINK_DEG, color="C0", ls="--", lw=0.8)
    ax.set_ylim(min(-5.0, min(excess)), max(30.0, max(excess)))
    ax.set_xlabel("time since the throw began [s]")
    ax.set_ylabel("median turning beyond lowered gently (+ hold) [deg]", color="C0")
    speed = ax.twinx()
    speed.semilogy(wait.t, np.maximum(wait.end_speed, 1e-4), color="C3", lw=0.8)
    speed.axhline(rest, color="C3", ls="--", lw=0.8)
    speed.set_ylim(1e-3, 10.0)
    speed.set_ylabel("free-end speed [m/s] (dashed: the lab's rest)", color="C3")
