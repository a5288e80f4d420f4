"""The learner: Bezier command, robot model, rope model, linearisation, inverse-model QP,
initial guess and the ILC loop. Imports only the core; never reads simulator state.
"""
