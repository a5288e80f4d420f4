"""The learner settings every shipped scenario file shares, and the paper's.

The scenario files (``scenarios/*.toml``) each write the shipped settings in their
``[defaults]``, with the reason beside them; the names here are what the rest of the
application takes as "the scenarios'": the gym envs and the baselines start from
:data:`SCENARIO_DEMO` with :data:`SCENARIO_WINDOW` and score with :func:`scenario_weights`,
``flyknot diagnose floor --demo`` too (``tests/test_scenario.py`` holds every file to them).
:data:`PAPER_SETTINGS` are the paper's (``flyknot run --paper-settings``).
"""

from __future__ import annotations

from dataclasses import replace

from learner.inverse_qp import InverseModelWeights

FOLLOW_WEIGHTS = ("w_pc", "w_vc", "w_rc", "w_pft", "w_vft", "w_rft")
"""The follow-through term's weights of :class:`learner.inverse_qp.InverseModelWeights`."""

PAPER_SETTINGS = (
    "objective=critical",
    "gain=1",
    "step=gain",
    "jacobian=model",
    "follow_through=true",
    "converged_knot=false",
    "weights.w_control=0.5",
    "weights.w_crit_vel=0.00375",
    *(f"weights.{w}={getattr(InverseModelWeights(), w):g}" for w in FOLLOW_WEIGHTS),
    "rope_model.stiffness=1e5",
    "rope_model.damping=50",
    "path_frac=0.05",
    "follow_through_s=0.035",
)
"""The paper's learner settings (``flyknot run --paper-settings``, laid over a scenario's defaults
and under each run's own fields): the critical-point objective, ILC gain 1 with the fixed-gain
step, the rope model's own Jacobian, the follow-through term, the stop at the first knot,
control weight 0.5, the critical point's velocity weight 0.00375, the follow-through weights of
the paper's appendix (``InverseModelWeights``' defaults), rope model bending stiffness 1e5 and
damping 50, the demonstration window from 5 % of the hand path to t_c + 35 ms (Suresh &
Atkeson; the scenario files' own values and why they differ: README "Learner settings")."""

SCENARIO_DEMO = "fast-paced"
"""The demonstration every shipped scenario learns rope 1 from: a person's throw at a person's
pace (``assets/demos/README.md``). The gym envs, the baselines and ``flyknot model-check``
start from it unless given another, so that they start where ILC does."""

SCENARIO_WINDOW = (0.25, 0.0)
"""The shipped scenarios' demonstration window ``(follow_through_s, path_frac)``: t_f - t_c =
0.25 s, t_0 at the start of the hand motion (README "Learner settings"; the paper's is
``(FOLLOW_THROUGH_S, PATH_FRAC)``, the defaults of
:class:`flyknot_app.scenario.RunSpec`)."""

SCENARIO_CRIT_VEL_WEIGHT = 0.1
"""The critical point's marker velocity weight w_crit_vel [s^2/m^2] of every shipped
scenario (each file's ``[defaults] weights``): a velocity error counts as the position error
it makes in dt = sqrt(0.1 / 25) = 63 ms, where this lab's knot is decided 65-106 ms after the
first self-contact (``flyknot diagnose decided``); the paper's 0.00375 is 12 ms."""

SCENARIO_FOLLOW_SHARE = 0.1
"""The share of the paper's follow-through weights (:data:`FOLLOW_WEIGHTS`) every shipped
scenario uses (``docs/measuring-sticks.md``, "The follow-through term at the scenarios'
velocity weight")."""


def scenario_weights() -> InverseModelWeights:
    """The shipped scenarios' QP weights: the paper's with w_crit_vel =
    :data:`SCENARIO_CRIT_VEL_WEIGHT` and the follow-through weights at
    :data:`SCENARIO_FOLLOW_SHARE` of the paper's. The gym envs' reward, the baselines' search
    and ``flyknot diagnose floor --demo`` score the critical point with them, so that every
    learner and measuring stick is scored on the objective ILC learns on."""
    paper = InverseModelWeights()
    follow = {w: round(SCENARIO_FOLLOW_SHARE * getattr(paper, w), 12) for w in FOLLOW_WEIGHTS}
    return replace(paper, w_crit_vel=SCENARIO_CRIT_VEL_WEIGHT, **follow)
