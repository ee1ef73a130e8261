"""Synthetic data for benchmarks, tests, the warm-up and the examples: vessel phantoms (``phantom``), phantom
studies (``phantom_study``), grey DSA from a mask (``synthetic_dsa``), a clinical-like rig (``clinical_rig``),
segmentation errors (``segmentation_errors``), native (unsubtracted) XA runs from two generators that differ
(``native_run``: what they share; ``native_run_skull``; ``native_run_texture``), CTA / TOF-MRA heads around
the tree with their XA pair (``synthetic_volumes``; their DICOM series in ``synthetic_volume_dicom``), and partial
visibility: early filling, one injected branch, a model with an extra territory (``partial_filling``). Nothing on
the clinical path imports this package."""
