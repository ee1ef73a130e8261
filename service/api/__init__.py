"""The HTTP API, one module per concern; only :mod:`service.app` imports it.

* ``routes/``: one ``APIRouter`` per resource (registrations, tracking, artifacts, operations).
* ``intake/``: a submission into a job — ``submission`` (multipart), ``dicom_reference`` (JSON, DICOMweb),
  ``validation`` (the validator processes).
* ``schemas/``: what the API returns and documents (``jobs``, ``payloads``).
* ``deps`` (typed dependencies ``Ctx``, ``Principal``, ``OwnedJob``), ``lifespan`` (store, validators, executor,
  sweeper), ``prometheus`` (metrics), ``middleware``, ``handlers`` (problem+json), ``httpfaults``, ``openapi``
  (the document's patches), ``docs_offline`` (/docs and /redoc without a CDN).

:func:`service.app.create_app` only wires these together.
"""
