"""``retargetd.daemon.validate.checks``: validation against MuJoCo: the model built
from the calibrated skeleton, per-frame checks, joint limits, dynamics (ghost
force), rendering, and the live validator.
"""
