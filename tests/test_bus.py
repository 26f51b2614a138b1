"""Real Zenoh sessions on loopback, ports chosen at run time, multicast off."""

from __future__ import annotations

import dataclasses
import hashlib
import socket
import threading
import time

import pytest

from octolog.bus import Bus, BusConfig
from octolog.errors import BusError, StageError
from schemas import codec, topics


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def endpoints():
    ep = f"tcp/127.0.0.1:{_port()}"
    server = BusConfig(listen=(ep,), multicast_scouting=False, namespace="t")
    client = BusConfig(connect=(ep,), multicast_scouting=False, namespace="t")
    return server, client


def _busy(ms: float) -> None:
    """Burn CPU for about `ms` milliseconds (a slow consumer, not a synchronization)."""
    end = time.perf_counter() + ms / 1000
    buf = bytes(64 * 1024)
    while time.perf_counter() < end:
        hashlib.sha256(buf).digest()


def test_slow_consumer_gets_everything_in_order(endpoints):
    server, client = endpoints
    n, payload = 60, bytes(200_000)
    with Bus(server, "mapper", inbox_size=2) as sub, Bus(client, "tracker") as pub:
        sub.subscribe([topics.RGBD_END])
        sub.announce()
        pub.watch(["mapper"])
        pub.wait_for(["mapper"], timeout_s=20)
        p = pub.publisher(topics.RGBD_END)

        def produce() -> None:
            for i in range(n):
                # the topic's `count` field carries the sequence number; the padding makes it big
                p.put(codec.stream_end_msg("x" * len(payload) if i % 10 == 0 else "x", i))

        t = threading.Thread(target=produce)
        t.start()
        got = []
        deadline = time.monotonic() + 60
        while len(got) < n and time.monotonic() < deadline:
            r = sub.receive(timeout_s=1.0)
            if r is not None:
                got.append(int(r.decode().count))
                _busy(5)
        t.join(timeout=30)
    assert got == list(range(n))


def test_a_vanished_peer_is_reported(endpoints):
    server, client = endpoints
    with Bus(dataclasses.replace(server, peer_timeout_s=1.0), "mapper") as watcher:
        other = Bus(client, "tracker").__enter__()
        other.announce()
        watcher.watch(["tracker"])
        watcher.wait_for(["tracker"], timeout_s=20)
        other.close()
        deadline = time.monotonic() + 30
        with pytest.raises(StageError, match="the tracker stage disappeared"):
            while time.monotonic() < deadline:
                watcher.receive(timeout_s=0.2)


def test_waiting_for_an_absent_stage_times_out_clearly(endpoints):
    server, _ = endpoints
    with Bus(server, "replay") as bus:
        bus.watch(["tracker"])
        with pytest.raises(StageError, match="no tracker stage appeared within 1 s"):
            bus.wait_for(["tracker"], timeout_s=1.0)


def test_stream_shortfall_is_an_error(endpoints):
    server, _ = endpoints
    with Bus(dataclasses.replace(server, history=0), "mapper") as bus:
        bus.expect_count(topics.KEYFRAME, 5, 5)
        with pytest.raises(StageError, match="2 of 7 messages on t/tracker/keyframe never arrived"):
            bus.expect_count(topics.KEYFRAME, 5, 7)


def test_bad_zenoh_config(tmp_path):
    bad = tmp_path / "z.json5"
    bad.write_text("{ mode: 'peer', connect: { endpoints: 7 } }")
    with pytest.raises(BusError):
        Bus(BusConfig(zenoh_config=str(bad)), "x").__enter__()
    with pytest.raises(BusError, match="--mode"):
        BusConfig(mode="satellite").validate()
