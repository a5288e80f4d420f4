"""Fixed facts of the task, the robot's limits and the measurement rates, in one place.

Sources: the paper (Suresh & Atkeson, "Learning Dynamic Rope Manipulation Using
Task-Level Iterative Learning Control"), appendix tables "Inverse Model Parameters",
"Demonstration Tracking Parameters", "Rope Model Parameters" and the rope table.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# --- paths ---------------------------------------------------------------------------
PACKAGE_ROOT = Path(__file__).resolve().parent
REPO_ROOT = PACKAGE_ROOT.parent
ASSETS_DIR = REPO_ROOT / "assets"
SCENARIOS_DIR = REPO_ROOT / "scenarios"
XARM7_XML = ASSETS_DIR / "xarm7" / "xarm7.xml"
ROPE_TABLE = ASSETS_DIR / "ropes.toml"
DEMOS_DIR = ASSETS_DIR / "demos"

# --- robot ---------------------------------------------------------------------------
N_JOINTS = 7
JOINT_NAMES = tuple(f"joint{i}" for i in range(1, N_JOINTS + 1))

# Paper, appendix tables (inverse model / demonstration tracking): joint limits.
Q_MIN = np.array([-6.28, -1.8, -6.28, -0.19, -6.28, -1.69, -6.28])  # [rad]
Q_MAX = np.array([6.28, 1.9, 6.28, 3.92, 6.28, 3.14, 6.28])  # [rad]
QD_MAX = np.full(N_JOINTS, 3.14)  # [rad/s]
QDD_MAX = np.full(N_JOINTS, 100.0)  # [rad/s^2]
TAU_MAX = np.array([130.0, 130.0, 40.0, 40.0, 40.0, 20.0, 20.0])  # [N m]
# Newer xArm 7 serials have joint 4's lower limit at -0.1047 rad (xarm-python-sdk 1.18.4);
# hardware mode takes the stricter of this table and the connected robot's own.
Q4_MIN_NEW_SERIALS = -0.1047  # [rad]

for _a in (Q_MIN, Q_MAX, QD_MAX, QDD_MAX, TAU_MAX):
    _a.setflags(write=False)

# --- rates ---------------------------------------------------------------------------
COMMAND_RATE_HZ = 250.0  # robot command and joint measurement [Hz]
MARKER_RATE_HZ = 200.0  # motion capture [Hz]
MODEL_DT = 0.005  # learner rope model step [s]

# --- command parametrisation ---------------------------------------------------------
N_KNOTS = 8  # Bezier knots per row
N_BASE_ROWS = 3  # base-offset rows (x, y, z) [m]
N_ROWS = N_JOINTS + N_BASE_ROWS  # 10
N_VARS = N_ROWS * N_KNOTS  # 80: the command's decision variables, row-major (10, 8)

# --- rope and markers ----------------------------------------------------------------
ROPE_LENGTH = 1.1  # [m], all ropes
N_MARKERS = 11
MARKER_SPACING = 0.10  # [m] from the fingertip; the last marker sits at the free end
GRAVITY = 9.81  # [m/s^2]

# --- task ----------------------------------------------------------------------------
Z_MIN_TIP = 1.2  # [m] fingertip height above the floor at the start (initial guess)
FOLLOW_THROUGH_S = 0.035  # [s] t_f = t_c + 35 ms (demo timing selection)
PATH_FRAC = 0.05  # t_0 where 5 % of the hand path is travelled (demo timing selection)
SETTLE_S = 1.5  # [s] default settling time after a command before judging the knot

KNOT_OUTCOMES = ("unknot", "trefoil", "other")
