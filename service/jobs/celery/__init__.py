"""Scale-out on Celery: the app and task name (``app``), the API-side executor (``executor``), the worker (``worker``)."""
