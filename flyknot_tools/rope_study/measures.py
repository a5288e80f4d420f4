"""The rope study's tests (fast motion, knot-pull, timing, shape error) and model variants.

See :mod:`flyknot_tools.rope_study` for what each test measures.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import mujoco
import numpy as np

from flyknot_sim.rope_handle import marker_arclengths, points_at_arclength, polyline_length
from flyknot_sim.rope_table import RopeParams, SimSettings, get_rope, load_sim_settings
from flyknot_tools.rope_study.crossings import count_run_crossings, overhand_knot_vertices
from flyknot_tools.rope_study.harness import (
    SETTLE_S,
    HandMotion,
    build_harness,
    edge_strain,
    holder_targets,
    place_vertices,
    simulate,
)


# ----------------------------------------------------------------------------------------
# the tests
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Config:
    """One model configuration to measure."""

    rope: int = 1
    kind: str = "flex"
    segments: int | None = None
    timestep: float | None = None
    integrator: str = "discrete"
    settings: SimSettings | None = None
    twist: bool = False

    def rope_params(self) -> RopeParams:
        """The rope with this configuration's overrides."""
        p = get_rope(self.rope)
        over = {}
        if self.segments is not None:
            over["segments"] = self.segments
        if self.timestep is not None:
            over["timestep"] = self.timestep
        return replace(p, **over) if over else p

    def label(self) -> str:
        """Short description for tables."""
        p = self.rope_params()
        s = self.settings or load_sim_settings()
        return (
            f"rope {self.rope} {self.kind} n={p.segments} dt={p.timestep * 1e3:g}ms "
            f"{self.integrator} {s.solver} it={s.iterations}/{s.ls_iterations} "
            f"tol={s.tolerance:g} self={s.selfcollide}"
        )


def measure_fast_motion(
    cfg: Config,
    settle_s: float = SETTLE_S,
    motion: HandMotion | None = None,
    judge_knot: bool = True,
) -> dict:
    """Replay the reference hand motion, then hold still ``settle_s``; see module docstring."""
    p = cfg.rope_params()
    motion = HandMotion.load() if motion is None else motion
    h = build_harness(
        p, kind=cfg.kind, settings=cfg.settings, integrator=cfg.integrator, home=motion.pos[0]
    )
    dt = h.model.opt.timestep
    n_steps = round((motion.duration + settle_s) / dt)
    times = dt * np.arange(1, n_steps + 1)
    q, qd = holder_targets(motion, times, h.home)
    mujoco.mj_kinematics(h.model, h.data)  # holder at home (zero joints)
    if cfg.kind == "flex":
        h.rope.set_hanging(h.model, h.data)
    run = simulate(h, q, qd)
    strain = edge_strain(run.vertices, p.segment_length)
    total = polyline_length(run.vertices) / p.length - 1
    moving = run.t <= motion.duration + 0.2
    out = {
        "config": cfg.label(),
        "diverged": run.diverged,
        "wall_per_sim": run.wall_per_sim,
        "max_stretch": float(np.max(total[moving])),
        "max_edge_strain": float(np.max(strain[moving])),
        "crossings": count_run_crossings(run.vertices),
    }
    if judge_knot and not run.diverged:
        from flyknot.knot import classify_centreline

        out["knot_end"] = classify_centreline(run.vertices[-1])
        out["knot_any"] = any(
            classify_centreline(v) == "trefoil" for v in run.vertices[:: max(1, int(0.05 / dt))]
        )
    return out


def time_fast_motion(cfg: Config, repeats: int = 3, settle_s: float = 0.5) -> float:
    """Best-of-``repeats`` wall seconds per simulated second (``mj_step`` only) of the
    reference motion plus ``settle_s``; the best run is the least disturbed by other load."""
    p = cfg.rope_params()
    motion = HandMotion.load()
    h = build_harness(
        p,
        kind=cfg.kind,
        settings=cfg.settings,
        integrator=cfg.integrator,
        home=motion.pos[0],
        twist=cfg.twist,
    )
    dt = h.model.opt.timestep
    n_steps = round((motion.duration + settle_s) / dt)
    q, qd = holder_targets(motion, dt * np.arange(1, n_steps + 1), h.home)
    best = math.inf
    for _ in range(repeats):
        mujoco.mj_resetData(h.model, h.data)
        mujoco.mj_kinematics(h.model, h.data)
        if cfg.kind == "flex":
            h.rope.set_hanging(h.model, h.data)
        best = min(best, simulate(h, q, qd).wall_per_sim)
    return best


PULL_FORCE_FACTOR = 25.0
"""Knot-pull force cap in rope weights (rope + end weight): about the peak tension at the hand
in the fast reference motion (rope 1: 12.8 N = 21 weights; rope 4: 4.8 N = 24; rope 5:
21.8 N = 11)."""


PULL_HOLDER_MASS = 0.05
"""Holder mass in the knot-pull [kg]: light, so the force cap (not the holder's momentum)
bounds the tension when the knot jams."""


def measure_knot_pull(
    cfg: Config,
    speed: float = 4.0,
    hold_s: float = 0.4,
    force_cap: float | None = None,
    self_collide: bool = True,
    knot_length: float = 0.7,
) -> dict:
    """Pull a loose overhand knot tight at ``speed`` (see module docstring).

    Args:
        cfg: Model configuration.
        speed: Pull speed of the holder [m/s].
        hold_s: Time held still after the pull [s].
        force_cap: Force cap of the holder's slides [N] (default ``PULL_FORCE_FACTOR`` times
            the weight of rope + end weight).
        self_collide: False disables all contacts (to show that the crossing check works).
        knot_length: Rope length in the initial loose knot [m].
    """
    from flyknot.knot import classify_centreline

    p = cfg.rope_params()
    if force_cap is None:
        force_cap = PULL_FORCE_FACTOR * (p.mass + p.end_mass) * 9.81
    x = overhand_knot_vertices(p, knot_length)
    axis = x[1] - x[0]
    settings = cfg.settings or load_sim_settings()
    home = x[0] - p.clearance * axis / np.linalg.norm(axis)
    h = build_harness(
        p,
        kind=cfg.kind,
        settings=settings,
        integrator=cfg.integrator,
        home=home,
        axis=axis,
        slide_force=force_cap,
        free_end_at=x[-1],
        holder_mass=PULL_HOLDER_MASS,
    )
    place_vertices(h, x)
    knot0 = classify_centreline(h.vertices())
    dt = h.model.opt.timestep
    pull_s = 0.6 / speed
    n_steps = round((pull_s + hold_s) / dt)
    times = dt * np.arange(1, n_steps + 1)
    q = np.zeros((n_steps, 6))
    qd = np.zeros((n_steps, 6))
    q[:, 2] = speed * np.minimum(times, pull_s)
    qd[:, 2] = np.where(times < pull_s, speed, 0.0)
    if not self_collide:
        h.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    run = simulate(h, q, qd)
    return {
        "config": cfg.label(),
        "force_cap": force_cap,
        "knot_before": knot0,
        "diverged": run.diverged,
        "crossings": count_run_crossings(run.vertices),
        "knot_after": classify_centreline(run.vertices[-1]) if not run.diverged else "-",
        "max_edge_strain": float(edge_strain(run.vertices, p.segment_length).max()),
        "end_gap": float(np.linalg.norm(run.vertices[-1, 0] - run.vertices[-1, -1])),
        "wall_per_sim": run.wall_per_sim,
    }


KNOT_LENGTHS = (0.6, 0.636, 0.671, 0.707, 0.743, 0.779, 0.814, 0.85)
"""Initial loose-knot sizes of the repeated knot-pull (the outcome is sensitive to details)."""


def measure_knot_pulls(
    cfg: Config, knot_lengths: Sequence[float] = KNOT_LENGTHS, self_collide: bool = True
) -> dict:
    """:func:`measure_knot_pull` once per initial knot size; counts kept knots and crossings."""
    runs = [measure_knot_pull(cfg, knot_length=k, self_collide=self_collide) for k in knot_lengths]
    return {
        "config": cfg.label(),
        "force_cap": runs[0]["force_cap"],
        "kept": sum(r["knot_after"] == "trefoil" for r in runs),
        "trials": len(runs),
        "crossings": sum(r["crossings"] for r in runs),
        "diverged": sum(r["diverged"] for r in runs),
        "max_edge_strain": max(r["max_edge_strain"] for r in runs),
        "wall_per_sim": float(np.mean([r["wall_per_sim"] for r in runs])),
    }


def measure_shape_error(cfg: Config, ref: Config, t_end: float = 0.5) -> dict:
    """Marker deviation of ``cfg`` from a finer ``ref`` model under the reference motion.

    Both replay the reference hand motion up to ``t_end`` (before the rope first touches
    itself); the 11 markers are compared at the coarser model's frames:
    e = |m_cfg(t) - m_ref(t)| per marker and time.

    Returns:
        ``rms`` and ``max`` of e [m].
    """
    motion = HandMotion.load()
    marks = []
    for c in (cfg, ref):
        p = c.rope_params()
        h = build_harness(
            p,
            kind=c.kind,
            settings=c.settings,
            integrator=c.integrator,
            home=motion.pos[0],
            twist=c.twist,
        )
        dt = h.model.opt.timestep
        n_steps = round(t_end / dt)
        times = dt * np.arange(1, n_steps + 1)
        q, qd = holder_targets(motion, times, h.home)
        mujoco.mj_kinematics(h.model, h.data)
        if c.kind == "flex":
            h.rope.set_hanging(h.model, h.data)
        run = simulate(h, q, qd)
        mk = points_at_arclength(run.vertices, p.segment_length, marker_arclengths(p.length))
        marks.append((run.t, mk))
    (t0, m0), (t1, m1) = marks
    idx = np.clip(np.searchsorted(t1, t0 - 1e-9), 0, len(t1) - 1)
    e = np.linalg.norm(m0 - m1[idx], axis=-1)
    return {"rms": float(np.sqrt(np.mean(e**2))), "max": float(e.max())}


VARIANTS: dict[str, dict] = {
    "chosen": {},
    "twist dofs (flexcomp)": {"twist": True},
    "40 segments": {"segments": 40},
    "20 segments": {"segments": 20},
    "dt 2 ms": {"timestep": 0.002},
    "contact solref 4 ms": {"settings": {"contact_timeconst": 0.004}},
    "capsule chain, implicit": {"kind": "chain", "integrator": "implicit"},
}
"""Model variants of the comparison table (changes from the rope table's settings)."""


def variant_config(rope: int, changes: dict) -> Config:
    """The :class:`Config` of a variant of :data:`VARIANTS` for one rope."""
    ch = dict(changes)
    over = ch.pop("settings", None)
    settings = replace(load_sim_settings(), **over) if over else None
    return Config(rope=rope, settings=settings, **ch)


def measure_variant(rope: int, name: str) -> dict:
    """All measurements of one rope and variant (fast motion, 8 knot-pulls, best-of-4 timing
    of the fast motion)."""
    cfg = variant_config(rope, VARIANTS[name])
    t0 = time.perf_counter()
    fast = measure_fast_motion(cfg)
    pull = measure_knot_pulls(cfg)
    fast["wall_per_sim"] = min(fast["wall_per_sim"], time_fast_motion(cfg))
    return {
        "rope": rope,
        "variant": name,
        "config": cfg.label(),
        "fast": fast,
        "pull": pull,
        "elapsed_s": time.perf_counter() - t0,
    }
