"""Submission as a service layer, shared by the HTTP API, the DICOM node and the CLI: typed inputs in, a queued
job out, or a refusal (:mod:`.refusals`) the caller turns into its own answer (an HTTP problem, a DIMSE retry,
a log line). This package knows nothing of HTTP."""
