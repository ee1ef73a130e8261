"""A submission becomes a job: the multipart form (``submission``), a DICOMweb reference (``dicom_reference``),
and the validator processes that open the stored inputs before a job is queued (``validation``)."""
