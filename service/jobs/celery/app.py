"""The Celery app shared by the API side (:mod:`service.jobs.celery.executor`) and the worker side
(:mod:`service.jobs.celery.worker`): the task name and the Celery settings. See the executor's module
docstring for how messages, leases and the job table fit together.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ...settings import ServiceSettings

TASK_NAME = "dsareg.run_job"


def celery_config(settings: ServiceSettings) -> dict[str, Any]:
    """Celery settings, each with the reason it is there."""
    timeout = settings.jobs.job_timeout_seconds
    vt = settings.effective_visibility_timeout
    return {
        "broker_url": settings.celery.broker_url,
        # nothing reads Celery results: the job table holds them
        "task_ignore_result": True,
        "result_backend": None,
        "task_serializer": "json",
        "accept_content": ["json"],
        "task_default_queue": settings.celery.celery_queue,
        # ack only after the task returned: a worker that dies mid-job leaves its message
        # unacked, so the broker delivers it again instead of forgetting the job
        "task_acks_late": True,
        # when a pool child is killed (OOM killer, SIGKILL) requeue the message rather than
        # acking it as failed (prefork pool; with solo/threads the whole process dies and the
        # message stays unacked anyway)
        "task_reject_on_worker_lost": True,
        # a worker reserves only the job it runs (with acks_late the running message counts):
        # registrations take seconds to minutes, so prefetched messages would wait behind a
        # long job while another worker is idle
        "worker_prefetch_multiplier": 1,
        # Redis redelivers a message not acked within the visibility timeout. It must be longer
        # than the longest job, else a healthy long job is delivered to a second worker (which
        # would then find it running and drop it — harmless but noisy). Worker death is
        # detected much sooner by the job lease; this is only the broker's fallback.
        # The sweep that restores expired unacked messages runs every interval * throttle seconds
        # (kombu default 10 * 10); a scan every interval (at most 10 s) is cheap (one ZRANGE).
        "broker_transport_options": {
            "visibility_timeout": int(vt),
            "unacked_restore_interval": max(1, min(10, int(vt / 4))),
            "unacked_restore_throttle": 1,
            "socket_connect_timeout": 5,
        },
        # time limits a bit above the engine's own job timeout (which the worker enforces
        # through should_stop and reports as a clean 'failed' job). Celery enforces these only
        # with the prefork pool; with solo/threads the job timeout is the limit.
        "task_soft_time_limit": int(timeout + 120),
        "task_time_limit": int(timeout + 300),
        # publishing must not hang a request when the broker is down: a couple of quick
        # retries, then the job stays queued in the table and the sweeper re-sends it
        # (the API side bounds every socket wait too: publisher_config)
        "task_publish_retry": True,
        "task_publish_retry_policy": {"max_retries": 2, "interval_start": 0, "interval_step": 0.2, "interval_max": 0.5},
        "broker_connection_timeout": 2.0,
        "broker_connection_retry_on_startup": True,
        "broker_connection_max_retries": None,  # a worker keeps trying while Redis restarts
        "worker_cancel_long_running_tasks_on_connection_loss": False,  # the lease protects the job
        "worker_hijack_root_logger": False,
        "worker_send_task_events": False,
        "task_track_started": False,
    }


def publisher_config(settings: ServiceSettings) -> dict[str, Any]:
    """The API side's broker bounds: a publish (or revoke, or queue-length probe) on a down or
    frozen Redis gives up within about ``broker_publish_timeout_seconds``.

    A frozen Redis accepts TCP connections (the kernel does) and never answers, so without a
    socket timeout redis-py waits forever and kombu's retry policy never gets to count; here
    every connect and every command waits at most a quarter of the budget, and the publish is
    tried twice (the second attempt reconnects: a Redis restart leaves a dead pooled connection
    that fails at once). The job is already in the table; the sweeper re-sends it
    (``CeleryExecutor.maintain``). Worker processes keep the defaults (long BRPOP polls).
    """
    step = settings.celery.broker_publish_timeout_seconds / 4.0
    return {
        "broker_transport_options": {
            **celery_config(settings)["broker_transport_options"],
            "socket_timeout": step, "socket_connect_timeout": step,
            # kombu's own reconnect loop (Connection.ensure_connection): one quick retry
            "max_retries": 1, "interval_start": 0, "interval_step": step, "interval_max": step,
        },
        "broker_connection_timeout": step,
        "broker_connection_max_retries": 1,
        "task_publish_retry_policy": {"max_retries": 1, "interval_start": 0, "interval_step": step,
                                      "interval_max": step},
    }


def make_celery(settings: ServiceSettings, task: Callable[..., Any] | None = None):
    """The Celery app; ``task`` (the worker's task body) is registered as ``TASK_NAME`` on the worker side.

    The API side only publishes ``TASK_NAME`` by name, so it needs no task body.
    """
    from celery import Celery

    app = Celery("dsareg", set_as_current=False)
    app.conf.update(celery_config(settings))
    if task is None:  # the API side only publishes: bounded waits on the broker
        app.conf.update(publisher_config(settings))
    if task is not None:
        app.task(name=TASK_NAME, bind=True, acks_late=True, reject_on_worker_lost=True,
                 max_retries=settings.celery.task_max_retries)(task)
    app.dsareg_settings = settings
    return app
