"""flyknot: a testbed for learning the overhand flying knot with Task-Level ILC.

The package ``flyknot`` holds what both sides of the seam share: the error family,
constants and limits, the data that crosses between a cell and the learner
(:class:`~flyknot.record.JointCommand`, :class:`~flyknot.record.TrialRecord`,
:class:`~flyknot.record.Cell`) and the command line. ``flyknot_sim`` is the simulated lab,
``learner`` is what runs in the real lab.
"""

__version__ = "0.1.0"
