"""Constructed rope centrelines with a known verdict, for the judge's tests.

Every curve hangs from its held end (first point) along -z in the lab frame, its knot about
``HANG_Z`` above the floor (z = 0); the tube leaves the held end along ``TUBE_AXIS`` (out of
the tube, the direction the rope leaves it).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from flyknot.verdict import KNOT, UNKNOTTED, WRAPPED_AT_GRIP, Verdict

TUBE_AXIS = np.array([0.0, 0.0, -1.0])
"""Out of the tube: the rope leaves the tube downward."""

HANG_Z = 1.5
"""[m] Height of a knot (or of a straight rope's held end) above the lab's floor: a rope
hanging from a fingertip above 1.2 m (``flyknot.constants.Z_MIN_TIP``)."""
_UP = np.array([0.0, 0.0, HANG_Z])


def _segment(a: np.ndarray, b: np.ndarray, spacing: float) -> np.ndarray:
    """Points from a to b (a included, b excluded), about ``spacing`` apart."""
    n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
    return a + (b - a) * (np.arange(n) / n)[:, None]


def _with_tails(knot: np.ndarray, above: float, tail: float, spacing: float) -> np.ndarray:
    """``knot`` (its first point the top, its last the bottom) with a straight rope of
    ``above`` [m] up to the held end and a free tail of ``tail`` [m] below it."""
    top, bottom = knot[0], knot[-1]
    held = top + np.array([0.0, 0.0, above])
    free = bottom - np.array([0.0, 0.0, tail])
    rope = np.vstack([_segment(held, top, spacing), knot, _segment(bottom, free, spacing), free])
    return rope + _UP


def trefoil_arc(scale: float, n: int = 60) -> np.ndarray:
    """The (2, 3) torus trefoil T(t) = (sin t + 2 sin 2t, cos t - 2 cos 2t, -sin 3t), opened
    at its outer rim t = pi, t in [pi + 0.2, 3 pi - 0.2]: starts just above z = 0, ends just
    below, (n, 3) [m]."""
    t = np.linspace(np.pi + 0.2, 3 * np.pi - 0.2, n)
    return scale * np.stack(
        [np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)], 1
    )


def figure_eight_arc(scale: float, n: int = 80) -> np.ndarray:
    """The figure-eight knot (Lissajous form: (cos 2t + ..)) opened at a point on its top,
    (n, 3) [m]: x = (2 + cos 2t) cos 3t, y = (2 + cos 2t) sin 3t, z = sin 4t."""
    t = np.linspace(0.02, 2 * np.pi - 0.02, n) + np.pi / 8
    r = 2 + np.cos(2 * t)
    arc = scale * np.stack([r * np.cos(3 * t), r * np.sin(3 * t), np.sin(4 * t)], 1)
    return arc


def overhand(
    *, above: float, tail: float, scale: float = 0.012, spacing: float = 0.03
) -> np.ndarray:
    """An overhand knot ``above`` [m] below the held end and ``tail`` [m] above the free end;
    ``scale`` 0.012 is a tight knot (3.6 cm across), 0.03 a loose one."""
    return _with_tails(trefoil_arc(scale), above, tail, spacing)


def figure_eight(*, above: float = 0.4, tail: float = 0.3, scale: float = 0.015) -> np.ndarray:
    """A figure-eight knot in the hanging rope."""
    return _with_tails(figure_eight_arc(scale), above, tail, 0.03)


def loop_round_held_end(*, radius: float = 0.03, drop: float = 1.0, n: int = 40) -> np.ndarray:
    """The rope leaves the tube, loops once round the tube just above its tip, and hangs:
    a wrap at the grip (the tube is the held end's continuation up the z axis)."""
    t = np.linspace(0.0, 2 * np.pi, n)
    z = 0.02 - 0.05 * t / (2 * np.pi) * -1  # climbs 5 cm up the tube while it turns
    loop = np.stack([radius * np.sin(t), radius * (1 - np.cos(t)) - radius, z - 0.02], 1)
    loop = np.vstack([[0.0, 0.0, 0.0], [0.0, -radius, -0.01], loop[1:]])
    last = loop[-1]
    hang = _segment(last + np.array([0.0, 0.0, -0.03]), last - np.array([0.0, 0.0, drop]), 0.03)
    return np.vstack([loop, hang, last - np.array([0.0, 0.0, drop])]) + _UP


def straight(length: float = 1.1, n: int = 31) -> np.ndarray:
    """A rope hanging straight down."""
    return np.stack([np.zeros(n), np.zeros(n), HANG_Z - np.linspace(0.0, length, n)], 1)


def transformed(points: np.ndarray, rotation: np.ndarray, shift: np.ndarray, scale: float):
    """``scale * R p + shift`` for every point."""
    return scale * points @ rotation.T + shift


def verdict(klass: str) -> Verdict:
    """A verdict of class ``klass`` as the lab would record it (votes and core made up)."""
    if klass == KNOT:
        return Verdict(KNOT, "trefoil", {"trefoil": 31}, (12, 22), 0.4)
    if klass == WRAPPED_AT_GRIP:
        return Verdict(WRAPPED_AT_GRIP, "trefoil", {"trefoil": 31}, (0, 10), 0.0)
    return Verdict(UNKNOTTED, "unknot", {"unknot": 31})


def judged(record, tied: bool):
    """``record`` with a knot in the hanging rope (``tied``) or an unknot, verdict included."""
    v = verdict(KNOT if tied else UNKNOTTED)
    return dataclasses.replace(record, knot=v.knot, verdict=v)


def end_in_its_loop(*, above: float = 0.4) -> np.ndarray:
    """An overhand knot whose free end stops half way through the loop: whether it is knotted
    depends on which way the end is closed (no supermajority: ambiguous)."""
    arc = trefoil_arc(0.03, 80)[:70]
    rope = np.vstack([_segment(arc[0] + np.array([0.0, 0.0, above]), arc[0], 0.03), arc])
    return rope + _UP
