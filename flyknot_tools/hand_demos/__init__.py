"""Synthetic human demonstrations of the flying knot: score, search, variants, synthesis.

A person ties the overhand flying knot with one hand: from rest, an upward twisting motion
throws a loop, an arc strikes near the rope's end so the end flips through the loop, and a
follow-through brings the hand to rest. That motion is a small family
(:class:`flyknot_sim.hand_motion.KnotMotion`), played by the free hand of
:mod:`flyknot_sim.hand`; this offline tool searches it with CMA-ES for members that tie the knot
and keep tying it under the lab's trial-to-trial variation, and records them as demonstrations
(``flyknot-tools demo synthesize``). Replaying a stored demonstration is part of the simulated
lab (:mod:`flyknot_sim.hand_replay`, ``flyknot demo replay``). How the search works:
``docs/demo-synthesis.md``; the shipped files' budgets and hit rates:
``assets/demos/README.md``.

Modules:

* :mod:`~flyknot_tools.hand_demos.reference`: the search seed, the family member fitted to the
  feasibility study's hand motion (data in ``flyknot_tools/data``).
* :mod:`~flyknot_tools.hand_demos.score`: the score of one trial and the writhe it credits.
* :mod:`~flyknot_tools.hand_demos.variants`: Fast, Slow, Swipe, Inverse and the search box.
* :mod:`~flyknot_tools.hand_demos.search`: evaluation of a motion and the CMA-ES search.
* :mod:`~flyknot_tools.hand_demos.synthesis`: staged search, recording and check of a
  demonstration.
"""
