"""The compiled self-contact scan (flyknot_sim.contact_kernel) against the NumPy one."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot_sim import rope_handle
from flyknot_sim.contact_kernel import self_contact_span
from flyknot_sim.lab import LabParams, SimLab

N_SEG = 30
FLEX = 0
END = 7


def _numpy_span(bound, data):
    pairs = rope_handle.BoundRope.self_contact_elements(bound, data)
    return (-1, -1) if len(pairs) == 0 else (int(pairs.min()), int(pairs.max()))


@st.composite
def contact_lists(draw):
    """MuJoCo-like contact lists: flex-flex, flex-geom (the end weight or another geom) and
    geom-geom contacts, some excluded, with room past ``ncon`` holding junk."""
    k = draw(st.integers(0, 12))
    rows = []
    for _ in range(k + 3):
        kind = draw(st.sampled_from(["ff", "ff", "fg", "gf", "gg"]))
        e0 = draw(st.integers(0, N_SEG - 1))  # neighbours and the free end's last elements
        e1 = min(N_SEG - 1, max(0, e0 + draw(st.integers(-3, 3))))  # are the edge cases
        e = [e0, e1] if kind == "ff" else [draw(st.integers(N_SEG - 4, N_SEG - 1))] * 2
        g = draw(st.sampled_from([END, 2, 3]))
        other_flex = draw(st.sampled_from([FLEX, 1]))
        flex = {"ff": [FLEX, other_flex], "fg": [other_flex, -1], "gf": [-1, other_flex]}
        geom = {"ff": [-1, -1], "fg": [-1, g], "gf": [g, -1], "gg": [g, 2]}
        f = flex.get(kind, [-1, -1])
        rows.append((f, [x if fl >= 0 else -1 for x, fl in zip(e, f, strict=True)], geom[kind]))
    flags = st.lists(st.sampled_from([0, 0, 0, 1]), min_size=k + 3, max_size=k + 3)
    exclude = np.array(draw(flags))
    flex, elem, geom = (np.array([r[i] for r in rows], dtype=np.int32) for i in range(3))
    return k, flex, elem, geom, exclude.astype(np.int32)


@settings(max_examples=300, deadline=None)
@given(contact_lists())
def test_the_compiled_scan_is_the_numpy_scan(case):
    ncon, flex, elem, geom, exclude = case
    data = SimpleNamespace(
        ncon=ncon, contact=SimpleNamespace(flex=flex, elem=elem, geom=geom, exclude=exclude)
    )
    bound = SimpleNamespace(flex_id=FLEX, end_geom=END, n_segments=N_SEG)
    want = _numpy_span(bound, data)
    got = self_contact_span(flex, elem, geom, exclude, ncon, FLEX, END, N_SEG)
    assert tuple(int(x) for x in got) == want


def test_the_lab_answers_the_same_both_ways_through_a_knotted_trial(monkeypatch):
    """A trial of rope 1 that ties (the robot demonstration's start, ``seeds/robot_knot.npz``,
    lab seed 10): the span and the contact flag at every tick of the motion and the first
    0.8 s of its settle, compiled and NumPy."""
    from flyknot.constants import DEMOS_DIR
    from learner.bezier import BezierCommand

    with np.load(DEMOS_DIR / "seeds" / "robot_knot.npz") as z:
        cmd = BezierCommand(z["knots"], float(z["T"])).joint_command()
    lab = SimLab(LabParams(rope=1, seed=10))
    session = lab.start(np.asarray(cmd.q[0]))
    b, d, m = lab.plant.rope, lab.plant.data, lab.plant.model
    seen = set()
    for i, q in enumerate(list(cmd.q) + [cmd.q[-1]] * 200):
        session.send(np.asarray(q)) if i < cmd.n else session._advance(np.asarray(q))
        monkeypatch.setattr(rope_handle, "COMPILED", True)
        fast = (b.self_contact(m, d), b.self_contact_span(m, d))
        monkeypatch.setattr(rope_handle, "COMPILED", False)
        slow = (b.self_contact(m, d), b.self_contact_span(m, d))
        assert fast == slow
        seen.add(fast[0])
    assert seen == {True, False}  # the trial has states with and without self-contact
