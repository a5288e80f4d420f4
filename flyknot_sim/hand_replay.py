"""Replaying a stored hand demonstration in the hand lab, on any rope.

A synthetic demonstration stores the motion it was made with (the 23 numbers of
:class:`flyknot_sim.hand_motion.KnotMotion`) and the hand lab's settings
(:data:`HAND_META_FIELDS`). :func:`replay` plays that motion again with the lab's
trial-to-trial variation (``flyknot demo replay FILE --rope N``), and :func:`save_replay`
writes one replay as a demonstration-like file (format in ``assets/demos/README.md``). The
demonstrations themselves are made by the offline demonstration search
(``flyknot-tools demo synthesize``, ``docs/demo-synthesis.md``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, RecordError
from flyknot.progress import bar_disable
from flyknot.verdict import Verdict
from flyknot_sim.hand import HandLab, HandTrial
from flyknot_sim.hand_motion import KnotMotion
from flyknot_sim.hand_params import HandParams, HandVariation
from flyknot_sim.mocap import MocapParams

REPLAY_GENERATOR = "flyknot_sim.hand_replay"
"""The ``generator`` in a saved replay's metadata (:func:`save_replay`)."""
REPLAY_GENERATOR_VERSION = 1
"""Bump when a change alters what a saved replay holds."""

HAND_META_FIELDS = (
    "home",
    "hand_mass",
    "hand_inertia",
    "hinge_armature",
    "slide_bandwidth",
    "hinge_bandwidth",
    "hang_s",
    "settle_s",
    "judge_rate_hz",
)
"""HandParams fields stored in a demonstration's metadata (replays rebuild the hand)."""


def hand_metadata(params: HandParams) -> dict[str, Any]:
    """The hand settings a replay needs, as plain data."""
    return {
        f: (list(getattr(params, f)) if f == "home" else getattr(params, f))
        for f in HAND_META_FIELDS
    }


def motion_from_demo(demo: Demonstration, source: str = "demonstration") -> KnotMotion:
    """The motion stored in a synthetic demonstration's metadata.

    Raises:
        RecordError: The metadata holds no motion (not made by the demonstration synthesis).
    """
    motion = demo.metadata.get("motion")
    if not isinstance(motion, Mapping):
        raise RecordError(
            f"{source}: no motion parameters in its metadata (only demonstrations made by "
            "`flyknot-tools demo synthesize` can be replayed)"
        )
    return KnotMotion.from_dict(motion)


def hand_from_demo(
    demo: Demonstration,
    rope: int | str,
    *,
    vary: bool = True,
    ropes: str | None = None,
    variation: HandVariation | None = None,
) -> HandParams:
    """The hand lab a demonstration was made in, holding rope ``rope`` (an id or a name,
    from ``ropes``, a user's ropes file, for a custom rope), with ``variation`` when
    ``vary`` (None: the lab's own, :class:`HandVariation`), else none."""
    stored = demo.metadata.get("hand", {})
    # The settle is the lab's own rule (judged at rest), not a fixed wait a demonstration
    # may have stored.
    kwargs = {f: stored[f] for f in HAND_META_FIELDS if f in stored and f != "settle_s"}
    if "home" in kwargs:
        kwargs["home"] = tuple(kwargs["home"])
    variation = (variation or HandVariation()) if vary else HandVariation.none()
    return HandParams(rope=rope, variation=variation, ropes=ropes, **kwargs)


@dataclass(frozen=True)
class ReplayResult:
    """Replays of a demonstration's motion.

    Attributes:
        rope: Rope id replayed with (a custom rope's name for a custom rope).
        outcomes: Settled knot type per replay (None if the simulation diverged).
        t_c: First rope self-contact per replay [s, demonstration clock], None if none.
        verdicts: The settled rope's verdict per replay (None if the simulation diverged).
        trials: The trials (kept only when asked for).
    """

    rope: int | str
    outcomes: tuple[str | None, ...]
    t_c: tuple[float | None, ...]
    verdicts: tuple[Verdict | None, ...] = ()
    trials: tuple[HandTrial, ...] = ()

    @property
    def knots(self) -> int:
        """Replays that ended with a knot in the hanging rope (verdict class ``knot``)."""
        return sum(v is not None and v.success for v in self.verdicts)

    def to_json(self) -> dict[str, Any]:
        """``{"repeats", "knots", "outcomes", "classes", "t_c"}``."""
        return {
            "repeats": len(self.outcomes),
            "knots": self.knots,
            "outcomes": list(self.outcomes),
            "classes": [None if v is None else v.klass for v in self.verdicts],
            "t_c": list(self.t_c),
        }


def replay(
    demo: Demonstration,
    *,
    rope: int | str | None = None,
    repeats: int = 1,
    seed: int = 0,
    vary: bool = True,
    settle_s: float | None = None,
    keep_trials: bool = False,
    variation: HandVariation | None = None,
    progress: bool = False,
    ropes: str | None = None,
) -> ReplayResult:
    """Play a synthetic demonstration's hand motion again, on any rope.

    Replay i draws its variation from ``np.random.default_rng([seed, i])`` (or none if not
    ``vary``: then, on the demonstration's rope, the hand trajectory and t_c are the
    demonstration's).

    Args:
        demo: A demonstration made by the demonstration synthesis (its metadata holds
            the motion).
        rope: Rope id or name (default: the demonstration's).
        repeats: Number of replays, >= 1.
        seed: Seed of the variations.
        vary: Apply the lab's trial-to-trial variation.
        settle_s: Settling time [s] (default: the demonstration's).
        keep_trials: Keep the trials in the result (memory: ~2 MB each).
        variation: The variation when ``vary`` (None: the hand lab's own).
        progress: Show a tqdm progress bar.
        ropes: A user's ropes file whose ropes ``rope`` may name.

    Raises:
        RecordError: The demonstration holds no motion.
        ConfigError: Bad rope id, repeats or settling time.
    """
    from tqdm import tqdm

    motion = motion_from_demo(demo)
    rope = demo.rope if rope is None else rope
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ConfigError("repeats", f"must be an integer >= 1, got {repeats!r}")
    hand = hand_from_demo(demo, rope, vary=vary, ropes=ropes, variation=variation)
    rope = hand.rope_params.id
    if settle_s is not None:
        hand = replace(hand, settle_s=settle_s)
    lab = HandLab(hand)
    outcomes, t_c, verdicts, trials = [], [], [], []
    for i in tqdm(range(repeats), desc=f"replay (rope {rope})", disable=bar_disable(progress)):
        rng = np.random.default_rng([seed, i]) if vary else None
        trial = lab.run(motion, rng)
        outcomes.append(trial.knot)
        verdicts.append(trial.verdict)
        t_c.append(trial.first_contact)
        if keep_trials:
            trials.append(trial)
    return ReplayResult(rope, tuple(outcomes), tuple(t_c), tuple(verdicts), tuple(trials))


REPLAY_TRUTH_RATE_HZ = 100.0
"""Rate of the true centrelines stored with a saved replay [Hz]."""


def save_replay(
    path: str | Path,
    trial: HandTrial,
    lab_rope: Any,
    *,
    rope: int | str,
    seed: int,
    index: int,
    source: str,
    mocap_params: MocapParams | None = None,
) -> Path:
    """Save one replay as a demonstration-like ``.npz`` (see ``assets/demos/README.md``).

    Arrays ``t``, ``hand_pos``, ``hand_quat``, ``markers`` (the capture's view, seeded by
    ``(seed, index, 3)``) and ``meta`` as in :meth:`Demonstration.save` (so a replay with a
    self-contact loads as a :class:`Demonstration`; ``t_c`` is null without one), plus the
    truth ``t_truth`` (m,) [s] and ``centreline`` (m, n + 1, 3) [m] at 100 Hz.

    Returns:
        The path written.
    """
    from flyknot.demo import DEMO_FORMAT_VERSION
    from flyknot_sim.mocap import emulate, sample_times

    mocap_params = MocapParams() if mocap_params is None else mocap_params
    rng = np.random.default_rng([seed, index, 3])
    t_m = sample_times(float(trial.t[-1]), mocap_params.rate_hz)
    markers = emulate(
        trial.t,
        lab_rope.markers_from_vertices(trial.vertices),
        t_m,
        trial.first_contact,
        mocap_params,
        rng,
    )
    pos = np.column_stack([np.interp(t_m, trial.t, trial.hand_pos[:, i]) for i in range(3)])
    quat = np.column_stack([np.interp(t_m, trial.t, trial.hand_quat[:, i]) for i in range(4)])
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    dt = float(trial.t[1] - trial.t[0])
    stride = max(1, round(1.0 / (REPLAY_TRUTH_RATE_HZ * dt)))
    meta = {
        "format_version": DEMO_FORMAT_VERSION,
        "t_c": trial.first_contact,
        "rope": rope,
        "metadata": {
            "generator": REPLAY_GENERATOR,
            "generator_version": REPLAY_GENERATOR_VERSION,
            "kind": "replay",
            "source": source,
            "index": index,
            "seed": seed,
            "outcome": trial.knot,
            "verdict": None if trial.verdict is None else trial.verdict.to_json(),
            "settle": None if trial.settle is None else dict(trial.settle),
            "variation": dict(trial.variation),
            "motion_start": trial.motion_start,
        },
    }
    params = getattr(lab_rope, "params", None)
    if getattr(params, "custom", False):  # a custom rope: the file's parameters
        meta["metadata"]["rope_params"] = params.to_dict()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        path,
        t=t_m,
        hand_pos=pos,
        hand_quat=quat,
        markers=markers,
        t_truth=trial.t[::stride],
        centreline=trial.vertices[::stride],
        meta=np.array(json.dumps(meta)),
    )
    return path
