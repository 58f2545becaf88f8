"""The automatic pose, scale and units of a scan, found without landmarks (:mod:`~statfit.registration.pose.search`)."""
