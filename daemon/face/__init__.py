"""``retargetd.daemon.face``: the face: face config, the stabilized blendshape solve
and its compiled kernel, and the shipped presets (``faces/``).
"""
