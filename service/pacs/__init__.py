"""PACS: the DICOMweb client (``dicomweb``) and the fetch before / STOW-RS after a job by reference (``dicom_jobs``);
the DICOM (DIMSE) node (``dimse``)."""
