"""tests/support/solo.py: a SOLO timed test runs alone; the others share; a waiting solo test is not starved."""

from __future__ import annotations

import threading
import time

from tests.support import solo


def _hold(folder, exclusive: bool, order: list[str], name: str, release: threading.Event) -> threading.Thread:
    def run() -> None:
        with solo.holding(folder, exclusive=exclusive):  # each thread opens its own files: flock tells them apart
            order.append(f"{name} in")
            release.wait(10)
            order.append(f"{name} out")

    thread = threading.Thread(target=run)
    thread.start()
    return thread


def test_shared_holders_overlap_and_an_exclusive_one_waits_for_them(tmp_path):
    order: list[str] = []
    release = threading.Event()
    first = _hold(tmp_path, False, order, "shared 1", release)
    second = _hold(tmp_path, False, order, "shared 2", release)
    time.sleep(0.3)
    assert sorted(order) == ["shared 1 in", "shared 2 in"]  # both at once
    alone = _hold(tmp_path, True, order, "solo", threading.Event())
    time.sleep(0.3)
    assert "solo in" not in order
    release.set()
    for thread in (first, second):
        thread.join(10)
    time.sleep(0.3)
    assert order[-1] == "solo in"
    alone.join(0.1)


def test_a_waiting_solo_holder_goes_before_a_later_shared_one(tmp_path):
    order: list[str] = []
    shared_done, solo_done, later_done = threading.Event(), threading.Event(), threading.Event()
    threads = [_hold(tmp_path, False, order, "shared", shared_done)]
    time.sleep(0.2)
    threads.append(_hold(tmp_path, True, order, "solo", solo_done))  # waits for the shared holder
    time.sleep(0.2)
    threads.append(_hold(tmp_path, False, order, "later", later_done))  # waits behind the solo one
    time.sleep(0.2)
    assert order == ["shared in"]
    shared_done.set()
    time.sleep(0.3)
    assert order == ["shared in", "shared out", "solo in"]
    solo_done.set()
    later_done.set()
    for thread in threads:
        thread.join(10)
    assert order[-2:] == ["later in", "later out"]
