"""The simulated lab: scene, arm servos with faults, ropes, air drag, mocap emulation, hand lab.

Imports only the core (``flyknot``); the learner never imports it.
"""
