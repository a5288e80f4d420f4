"""flyknot_hw: the real lab, an xArm 7 streamed at 250 Hz and a motion-capture system.

Imports only the core package ``flyknot`` (and, lazily, the xArm SDK); what it needs from the
learner or the application (inverse dynamics, fingertip kinematics, prompts) is passed in.
"""
