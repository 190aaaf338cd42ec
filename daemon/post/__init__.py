"""Post stages: the chapter's "Tips and Tricks" between the solve and the target.

Per-frame stages are objects built once (buffers preallocated from the skeleton) with
``apply(in, out) -> out``; they allocate nothing per call. Offline operations on whole
takes (resampling, gap filling, blending, loops, keyframe reduction) are functions.

- :mod:`~retargetd.daemon.post.pose`: :class:`PoseBuffer`, the per-frame pose.
- :mod:`~retargetd.daemon.post.twist`: twist distribution over a limb (5.59).
- :mod:`~retargetd.daemon.post.pivot`: shifting-pivot spine distribution;
  :class:`~retargetd.daemon.post.pivot.SpinePivot` on a retargeted frame (live).
- :mod:`~retargetd.daemon.post.hermite`: Hermite spine curve (5.60-5.61), and a target
  spine along it (``retarget --spread hermite``).
- :mod:`~retargetd.daemon.post.interp`: slerp at work (5.86-5.87): resample, fill,
  blend, loop; :class:`~retargetd.daemon.post.interp.RateResampler` for live output.
- :mod:`~retargetd.daemon.post.one_euro`: the One Euro filter, quaternion-aware.
- :mod:`~retargetd.daemon.post.reduce`: keyframe reduction with least-squares refit.
- :mod:`~retargetd.daemon.post.pipeline`: ``[[pipeline]]`` stages, in order, timed.
- :mod:`~retargetd.daemon.post.solve_post`: a pipeline on a body-solve pose in place
  (the live loop's stage, between the body solve and the target mapping).
"""
