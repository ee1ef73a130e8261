"""The test suite: ``unit/`` (one folder per engine/service package), ``system/`` (real servers: service, faults,
scaleout, dicom), ``support/`` (shared kits and throw-away servers)."""
