"""``retargetd.daemon.synth``: the synthetic performer: a known skeleton and its
motions, marker sets (``markersets/``), and the synthetic face with ground truth.
"""
