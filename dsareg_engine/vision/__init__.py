"""Image analysis of DSA frames: vessel segmentation (``segmentation``), the collimator border (``dsa_border``),
vessel coverage maps (``dsa_coverage``), the contrast onset frame (``vessel_onset``) and what a view's target is
(``vessel_target``: a mask or a coverage map), and the patient motion between a native run's mask and
contrast frames (``xa_motion``)."""
