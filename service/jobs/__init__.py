"""The job runtime: executors (``executor``; ``factory`` picks one), worker processes (``worker``), their
supervision (``procwatch``), the lease and retention sweeper (``sweeper``), and the Celery path (``celery/``).
Never imports ``service.api``."""
