"""The automatic pose, scale and units of a scan, found without landmarks: the search's steps in
order (:mod:`~statfit.registration.pose.search` says why each is there).

- :mod:`~statfit.registration.pose.frames`: poses between the model's and the scan's unit frames; a
  landmark similarity's units.
- :mod:`~statfit.registration.pose.hypotheses`: 60 starting rotations (and 60 more for a second
  look), the poses as arrays.
- :mod:`~statfit.registration.pose.icp`: trimmed point-to-plane ICP of every pose at once.
- :mod:`~statfit.registration.pose.refinement`: the best few refined with the first modes, then
  polished with every mode.
- :mod:`~statfit.registration.pose.scoring`: how well a pose explains the scan; refusing implausible
  scans.
- :mod:`~statfit.registration.pose.search`: :func:`~statfit.registration.pose.search.estimate_pose` and
  :func:`~statfit.registration.pose.search.refine_pose`, which run them.
"""
