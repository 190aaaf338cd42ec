"""``retargetd.daemon.props``: props and virtual cameras, rigid bodies tracked from
marker clusters beside the performers: a prop's marker layout calibrated from a still
frame (``layout``), and its per-frame weighted rigid fit with the gate, the robust
loss, the swap check and the hold (``kernel``, ``solve``).
"""
