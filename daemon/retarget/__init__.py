"""``retargetd.daemon.retarget.retarget``: the target side: the target skeleton and name
maps, the retargeter and its compiled kernel, and BVH export.
"""
