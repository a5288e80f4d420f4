"""Measurements that chose the rope model: stretch, tunnelling, knot-pull, speed, flying knot.

Run ``python -m flyknot_tools.rope_study`` (a few minutes on one core) to print the table of
``docs/rope-model.md``; ``--help`` lists the options.

The harness is a "holder" body with three slide and three hinge joints (about y, then x,
then z), each driven by a stiff position servo plus a velocity servo fed with the target's
derivative (feed-forward, so a 4 m/s hand does not lag). The rope hangs from the holder: a
1D flex built by :func:`flyknot_sim.rope.add_rope`, or, for comparison, a chain of capsules
on ball joints (:func:`flyknot_tools.rope_study.harness.add_capsule_chain`).

Tests:

* **fast motion**: the reference hand motion that tied a flying knot in the feasibility study
  (``flyknot_tools/data/reference_hand_motion_rope1.csv``, peak hand speed 3.9 m/s, 180+
  degree wrist turns), then 1.5 s still. Measured: largest stretch of the whole rope and of
  one edge, centreline crossings (tunnelling), wall seconds per simulated second, knot at the
  end.
* **knot-pull**: a loose overhand knot (an opened trefoil with straight tails) whose lower end
  is fixed while the holder pulls the upper end up at 4 m/s with a force cap, then holds.
  Measured: crossings, and whether the knot is still a trefoil after the pull.

Tunnelling is detected by :func:`flyknot_tools.rope_study.crossings.count_crossings`: between
two saved frames every vertex moves on a straight line, and two non-adjacent centreline
segments cross when their four end points become coplanar at a time at which the segments
intersect (a cubic in time, solved exactly on monotone brackets). With self-collision off
every test rope crosses itself, so the check can fail.

Modules: :mod:`~flyknot_tools.rope_study.harness` (hand motion, holder + rope scene,
simulation), :mod:`~flyknot_tools.rope_study.crossings` (continuous crossing check, loose
overhand knot), :mod:`~flyknot_tools.rope_study.measures` (the tests and model variants),
:mod:`~flyknot_tools.rope_study.cli` (``main(argv)``: the table).
"""
