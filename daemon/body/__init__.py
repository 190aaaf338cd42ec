"""``retargetd.daemon.body``: the body: rig files, calibration on a base pose, the per-
frame body solve and its compiled kernel, and the shipped rigs (``rigs/``).
"""
