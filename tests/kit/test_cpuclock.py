"""kit/cpuclock.py: thread CPU charged to named buckets, nested charges counted once."""

from __future__ import annotations

import threading
import time

from octolog.kit import cpuclock


def _spin(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_nested_charges_count_once_and_waiting_is_not_charged() -> None:
    before = cpuclock.report()["buckets"]
    with cpuclock.charge("test-outer"):
        _spin(0.05)
        with cpuclock.charge("test-inner"):
            _spin(0.05)
        time.sleep(0.2)  # waiting costs no CPU: not charged
        _spin(0.05)
    after = cpuclock.report()["buckets"]
    outer = after["test-outer"] - before.get("test-outer", 0.0)
    inner = after["test-inner"] - before.get("test-inner", 0.0)
    assert 0.1 <= outer < 0.15  # its own 0.1 s, not the inner's, not the sleep
    assert 0.05 <= inner < 0.1


def test_charges_from_threads_add_up_and_the_report_has_the_process() -> None:
    def work() -> None:
        with cpuclock.charge("test-threads"):
            _spin(0.03)

    before = cpuclock.report()["buckets"].get("test-threads", 0.0)
    threads = [threading.Thread(target=work) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    report = cpuclock.report()
    assert report["buckets"]["test-threads"] - before >= 0.09
    assert report["process"] >= report["buckets"]["test-threads"]
    assert set(report) == {"process", "children", "buckets", "threads"}
