"""Real Zenoh sessions on loopback, ports chosen at run time, multicast off."""

from __future__ import annotations

import dataclasses
import hashlib
import subprocess
import sys
import threading
import time

import pytest
from helpers import free_port

from octolog.kit.bus import Bus, BusConfig, wire
from octolog.kit.bus.publishing import History
from octolog.kit.errors import BusError, StageError
from octolog.schemas import codec, streammsgs, topics


@pytest.fixture
def endpoints():
    ep = f"tcp/127.0.0.1:{free_port()}"
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
                p.put(streammsgs.stream_end_msg("x" * len(payload) if i % 10 == 0 else "x", i))

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


def test_a_progress_topic_collapses_in_the_inbox_and_never_fills_it():
    """`latest_only` (the mapper takes a robot's tracker statuses so): statuses in a row collapse to
    the newest, in place between the data samples; a status never blocks on a full inbox whose
    last item is a status, while a data sample still does (back-pressure)."""
    from octolog.kit.bus.inbox import Inbox, Received

    def status(seq: int) -> Received:
        return Received(topics.TRACKING_STATUS, bytes([seq]))

    def data(name: str) -> Received:
        return Received(topics.KEYFRAME_END, name.encode())

    inbox = Inbox(4)
    inbox.keep_latest(topics.TRACKING_STATUS)
    for item in (status(1), status(2), data("a"), status(3), status(4), status(5), data("b")):
        inbox.put(item)
    got = []
    while (r := inbox.get_nowait()) is not None:
        got.append(r.payload)
    assert got == [bytes([2]), b"a", bytes([5]), b"b"]
    full = Inbox(2)
    full.keep_latest(topics.TRACKING_STATUS)
    full.put(data("a"))
    full.put(status(1))
    put = threading.Thread(target=full.put, args=(status(2),))
    put.start()
    put.join(timeout=30)  # a guard against a hang, not a synchronisation: the put returns at once
    assert not put.is_alive()
    blocked = threading.Thread(target=full.put, args=(data("b"),))
    blocked.start()
    assert full.get(1.0).payload == b"a"  # room: the blocked data sample goes in
    blocked.join(timeout=30)
    assert [full.get_nowait().payload, full.get_nowait().payload] == [bytes([2]), b"b"]


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


def test_the_transport_flags_import_neither_zenoh_nor_the_codec():
    """`octolog --help`, `eval` and `info` build a BusConfig while parsing: that must stay cheap."""
    from helpers import ROOT

    code = ("import sys, octolog.shell.args; "
            "print(sorted(m for m in ('zenoh', 'octolog.schemas.codec', 'octolog.kit.bus') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# --- recovery: sequence numbers, publisher history, late joiners -------------------------------


def test_numbering_and_history_queries_round_trip_through_the_wire_format():
    a, b, c = b"a" * 16, b"b" * 16, b"c" * 16
    att = wire.numbered_attachment(5, b, [wire.dependency(a, 7, 3)])
    assert wire.parse_numbered(att) == wire.Numbered(5, b, ((a, 7, 3),))
    assert wire.parse_numbered(b"a ROS bridge's") is None and wire.parse_numbered(att + b"x") is None
    assert wire.parse_history_reply(wire.history_attachment(2, att)) == (2, wire.parse_numbered(att))
    selector = wire.history_selector("t/k", [(b, 4, 9), (c, 0, None)])
    assert selector.startswith("t/k/@history/*?")
    params = dict(p.split("=") for p in selector.split("?")[1].split(";"))
    assert wire.requested_range(params, b) == (4, 9)
    assert wire.requested_range(params, c) == (0, None)
    assert wire.requested_range(params, a) == (0, None)  # not named: everything from `from`
    assert wire.requested_range({"from": "x"}, a) is None


def test_a_history_keeps_its_newest_samples_within_its_bounds():
    by_count = History(3, 1 << 20)
    for i in range(5):
        by_count.add(i, b"x", b"")
    oldest, items = by_count.since(3, 16)
    assert oldest == 2 and [seq for seq, _, _ in items] == [3, 4]
    by_bytes = History(None, 10)
    by_bytes.add(0, bytes(8), b"")
    by_bytes.add(1, bytes(8), b"")
    assert by_bytes.since(0, 16)[0] == 1
    by_bytes.add(2, bytes(100), b"")  # over the cap alone: the newest always stays
    assert [seq for seq, _, _ in by_bytes.since(0, 16)[1]] == [2]


NUMBERED = topics.Topic("test/numbered", "octolog_msgs/msg/StreamEnd")  # `count` carries the number


def _lose(p, i: int) -> None:
    """Sample `i` lost on the wire: numbered and kept in the publisher's history, never sent."""
    p._number(codec.encode(streammsgs.stream_end_msg("x", i), p.topic.msgtype))


def _numbers(bus: Bus, n: int, timeout_s: float = 30.0) -> list[int]:
    """What the inbox delivers until `n` samples came or nothing more comes within the timeout."""
    got: list[int] = []
    deadline = time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < deadline:
        r = bus.receive(timeout_s=0.5)
        if r is not None:
            got.append(int(r.decode().count))
    return got


def _connected(sub: Bus, pub: Bus, topic=NUMBERED) -> None:
    sub.subscribe([topic])
    sub.announce()
    pub.watch(["mapper"])
    pub.wait_for(["mapper"], timeout_s=20)


def test_lost_samples_are_recovered_once_and_in_order(endpoints):
    server, client = endpoints
    with Bus(server, "mapper") as sub, Bus(client, "tracker") as pub:
        _connected(sub, pub)
        p = pub.publisher(NUMBERED)
        for i in range(12):
            if i in (3, 4, 11):  # a gap in the middle (seen when 5 arrives) and a lost tail
                _lose(p, i)
            else:
                p.put(streammsgs.stream_end_msg("x", i))
        got = _numbers(sub, 12)
        assert got == list(range(12))
        assert sub.recovered == 3
        assert _numbers(sub, 1, timeout_s=2.5) == []  # nothing twice, even after idle probes


def test_topics_of_one_publisher_keep_their_order_across_a_recovery(endpoints):
    server, client = endpoints
    other = topics.Topic("test/other", NUMBERED.msgtype)
    with Bus(server, "mapper") as sub, Bus(client, "tracker") as pub:
        sub.subscribe([other])
        _connected(sub, pub)
        pa, pb = pub.publisher(NUMBERED), pub.publisher(other)
        pa.put(streammsgs.stream_end_msg("x", 0))
        pb.put(streammsgs.stream_end_msg("x", 0))
        _lose(pa, 1)
        pb.put(streammsgs.stream_end_msg("x", 1))  # sent after a1: must not overtake it
        pa.put(streammsgs.stream_end_msg("x", 2))
        got = []
        deadline = time.monotonic() + 30
        while len(got) < 5 and time.monotonic() < deadline:
            r = sub.receive(timeout_s=0.5)
            if r is not None:
                got.append((r.topic.name[-1], int(r.decode().count)))
        assert got == [("d", 0), ("r", 0), ("d", 1), ("r", 1), ("d", 2)]  # numbere(d), othe(r)


def test_late_subscriber_gets_the_history_then_live_exactly_once(endpoints):
    server, client = endpoints
    with Bus(server, "tracker") as pub:
        p = pub.publisher(topics.KEYFRAME_END)  # a keep-all stream: a late joiner gets it from 0
        for i in range(10):
            p.put(streammsgs.stream_end_msg("x", i))
        with Bus(client, "mapper") as sub:
            _connected(sub, pub, topics.KEYFRAME_END)
            for i in range(10, 20):
                p.put(streammsgs.stream_end_msg("x", i))
            assert _numbers(sub, 20) == list(range(20))
            assert _numbers(sub, 1, timeout_s=2.5) == []


def test_late_subscriber_starts_at_the_oldest_kept_sample(endpoints):
    server, client = endpoints
    with Bus(dataclasses.replace(server, history=4), "tracker") as pub:
        p = pub.publisher(NUMBERED)
        for i in range(10):
            p.put(streammsgs.stream_end_msg("x", i))
        with Bus(client, "mapper") as sub:
            sub.subscribe([NUMBERED])
            assert _numbers(sub, 4) == [6, 7, 8, 9]


def test_samples_older_than_the_history_are_reported_lost(endpoints):
    server, client = endpoints
    with Bus(server, "mapper") as sub, Bus(dataclasses.replace(client, history=1), "tracker") as pub:
        _connected(sub, pub)
        p = pub.publisher(NUMBERED)
        p.put(streammsgs.stream_end_msg("x", 0))
        assert _numbers(sub, 1) == [0]
        for i in range(1, 6):
            _lose(p, i)
        p.put(streammsgs.stream_end_msg("x", 6))  # the history keeps 6 only
        with pytest.raises(StageError, match="5 samples on t/test/numbered were lost for good"):
            _numbers(sub, 6)


def test_a_producer_lingers_until_its_consumer_is_done(endpoints):
    server, client = endpoints
    with Bus(server, "tracker") as prod:
        prod.watch(["mapper"], required=False)
        assert prod.linger("mapper") is False  # no mapper ever: nothing to wait for
        with Bus(client, "mapper") as cons:
            cons.announce()
            prod.wait_for(["mapper"], timeout_s=20)
        assert prod.linger("mapper") is True  # it said it finished


def test_a_producer_lingers_only_until_its_consumer_has_taken_its_input(endpoints):
    """A live camera waits for the tracker to take its frames, not for the tracker's last adjustment
    and the map behind it: the tracker's "taken" ends that linger while the tracker still runs."""
    server, client = endpoints
    with Bus(server, "recorder") as prod:
        prod.watch(["tracker"], required=False)
        with Bus(client, "tracker") as cons:
            cons.announce()
            prod.wait_for(["tracker"], timeout_s=20)
            cons.say_taken("frames")
            done: list[bool] = []
            t = threading.Thread(target=lambda: done.append(prod.linger("tracker", taken="frames")))
            t.start()
            t.join(120)  # a linger that missed the news would never return: a hang fails here
            assert done == [True]
            assert "tracker" not in prod._membership._done  # the tracker itself has not finished


def test_a_lingering_producer_drains_what_it_still_receives(endpoints):
    """A producer subscribed to its consumer's replies (a replay's status line) lingers while the
    consumer sends more than its inbox holds, then finishes: the replies reach `on_received` in
    order and the linger ends. Left in the inbox they would block the receive thread and the news
    of the end with it: the linger would never return (run in a thread, so a hang fails here)."""
    server, client = endpoints
    with Bus(server, "replay", inbox_size=4) as prod:
        prod.subscribe([NUMBERED])
        prod.watch(["tracker"], required=False)
        seen: list[int] = []
        with Bus(client, "tracker") as cons:
            cons.announce()
            prod.wait_for(["tracker"], timeout_s=20)
            p = cons.publisher(NUMBERED)
            for i in range(20):
                p.put(streammsgs.stream_end_msg("x", i))
        done: list[bool] = []
        t = threading.Thread(target=lambda: done.append(prod.linger("tracker", lambda r: seen.append(r.decode().count))))
        t.start()
        t.join(120)
        assert done == [True] and seen == list(range(20)), (done, seen)


def test_a_producer_stops_lingering_for_a_consumer_that_died(endpoints):
    server, client = endpoints
    with Bus(dataclasses.replace(server, peer_timeout_s=1.0), "tracker") as prod:
        prod.watch(["mapper"], required=False)
        with pytest.raises(RuntimeError), Bus(client, "mapper") as cons:
            cons.announce()
            prod.wait_for(["mapper"], timeout_s=20)
            raise RuntimeError("the mapper crashed")  # leaves without saying it is done
        assert prod.linger("mapper") is False  # gone for peer_timeout_s: given up


def test_a_bad_zenoh_config_file_is_one_line(tmp_path):
    bad = tmp_path / "zenoh.json5"
    bad.write_text('{ "mode": "peer", invalid json\n')
    with pytest.raises(BusError) as err:
        with Bus(BusConfig(zenoh_config=str(bad), multicast_scouting=False), "tracker"):
            pass
    msg = str(err.value)
    assert "\n" not in msg and str(bad) in msg and "1:11" in msg and ".rs:" not in msg, msg


_SYSCALLS = {"x86_64": {"tgkill": 234, "futex": 202}, "aarch64": {"tgkill": 131, "futex": 98}}


def _syscall_numbers() -> dict[str, int]:
    import platform

    if platform.machine() not in _SYSCALLS:
        pytest.skip(f"syscall numbers unknown on {platform.machine()}")
    return _SYSCALLS[platform.machine()]


def _signal_thread(pid: int, tid: int, sig: int) -> None:
    """tgkill(2): deliver `sig` to one thread of another process, as the kernel may do with a kill."""
    import ctypes
    import os

    libc = ctypes.CDLL(None, use_errno=True)
    if libc.syscall(_syscall_numbers()["tgkill"], pid, tid, sig) != 0:
        raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))


def test_router_stops_when_sigterm_lands_on_a_zenoh_thread():
    """A process-directed SIGTERM may be delivered to any thread that does not block it, here one of
    Zenoh's Rust threads; Python then runs its handler only when the main thread next runs bytecode.
    `octolog router` must still stop (exit 130), not sleep on forever (CI once hung on this)."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    from helpers import ROOT

    ep = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "octolog", "router", "--listen", ep], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        assert "router: listening on" in proc.stdout.readline()  # printed once its session is open
        tasks = Path(f"/proc/{proc.pid}/task")
        sigterm_bit = 1 << (signal.SIGTERM - 1)

        def takes_sigterm(tid: str) -> bool:
            blocked = next(ln for ln in (tasks / tid / "status").read_text().splitlines() if ln.startswith("SigBlk:"))
            return not int(blocked.split()[1], 16) & sigterm_bit

        zenoh_threads = sorted(t.name for t in tasks.iterdir() if int(t.name) != proc.pid
                               and (t / "comm").read_text().strip() in ("app-0", "net-0", "acc-0", "rx-0", "tx-0")
                               and takes_sigterm(t.name))
        assert zenoh_threads, "no Zenoh runtime thread found in the router process"
        # the signal must come while the main thread sleeps in a futex (its wait for the stop event),
        # not while it still runs Python code on the way there, where any handler would run at once.
        # Polled from /proc: the kernel gives no notice of another process's thread going to sleep.
        futex, deadline = _syscall_numbers()["futex"], time.monotonic() + 20
        while (tasks / str(proc.pid) / "syscall").read_text().split()[0] != str(futex):
            assert time.monotonic() < deadline, "the router's main thread never went to sleep"
            time.sleep(0.01)
        _signal_thread(proc.pid, int(zenoh_threads[0]), signal.SIGTERM)
        assert proc.wait(timeout=15) == 130
        assert "octolog router: interrupted" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
