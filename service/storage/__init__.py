"""Persistence: the job store (``store``, SQLAlchemy), input and artifact blobs in files (``blobs``) or in the
job database (``dbblobs``). Imports nothing else of the service."""
