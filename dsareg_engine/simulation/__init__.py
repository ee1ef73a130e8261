"""Synthetic data for benchmarks, tests, the warm-up and the examples: vessel phantoms (``phantom``), phantom
studies (``phantom_study``), grey DSA from a mask (``synthetic_dsa``), a clinical-like rig (``clinical_rig``) and
segmentation errors (``segmentation_errors``). Nothing on the clinical path imports this package."""
