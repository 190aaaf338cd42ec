"""``retargetd.daemon.live``: the live daemon: the loop that owns the sockets and the
solve, control and show control, config, stats, live recording and the live face
stage.
"""
