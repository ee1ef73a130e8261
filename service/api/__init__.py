"""The HTTP API, one module per concern.

* ``deps``: the typed dependencies every route uses (``Ctx``, ``Principal``, ``OwnedJob``).
* ``registrations`` / ``tracking`` / ``artifacts`` / ``operations``: one ``APIRouter`` per resource.
* ``submission`` (multipart) and ``dicom_reference`` (JSON, DICOMweb): parsing a submission into a job.
* ``lifespan`` (store, validators, executor, sweeper), ``metrics`` (Prometheus), ``handlers``
  (problem+json error handlers), ``openapi`` (the document's patches).

:func:`service.app.create_app` only wires these together.
"""
