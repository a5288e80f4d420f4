"""The rope validation suite: what every real rope of its kind does, measured on the lab's rope.

``flyknot-tools rope-validate [--ropes ...] [--quick] [--set FIELD=VALUE ...] [--json]`` runs
the cases of :mod:`flyknot_tools.rope_validate.cases` on each rope (the lab's rope model:
MuJoCo's flex with the rope table's values, air drag and the frictional bending couple, stepped
as the lab steps it, :mod:`flyknot_tools.rope_validate.bench`) and prints a table per rope:

* ``knot_hold``: a loose overhand knot with the end weight below it, hung and swung;
* ``static_hold``: the knot, pulled in by the end weight, does not slip over 60 s;
* ``capstan``: sliding over a fixed rod, the tension ratio is exp(mu theta);
* ``cantilever``: bending length from above and from below (a textile's hysteresis);
* ``spring_back``: a released 5 cm loop keeps (cotton) or loses (rubber) its bend;
* ``swing_decay``: a hanging rope's swing decays at least as fast as air drag makes it;
* ``rest_shape``: hung between two points it takes the catenary;
* ``rest_after_motion``: thrown as in a flying knot, after 10 s it has no kinks
  (:mod:`flyknot_tools.rope_validate.rest_after_motion`; a picture with ``--pictures DIR``).

Each case names its expectation for the rope's material and the source of it. The results
and the choice of the rope model they led to: ``docs/rope-model.md``.
"""
