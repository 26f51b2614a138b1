"""Transport benchmark: octolog's Bus (Zenoh) between two processes, against a raw memory copy.

    python bench/transport.py [--frames 200] [--small 20000] [--latency 300] [--wire]

Payloads: one 640x480 RGB-D frame as the replay publishes it (CDR of octolog_msgs/RgbdFrame, TUM
fr1/xyz frame 0 when ../shared/data is there, else the synthetic scene), and a small message (a
geometry_msgs/PoseStamped, as the tracker publishes per frame). Transports:

- memcpy: a copy of the same bytes in one process (numpy), the physical limit;
- shm: two processes on loopback, Zenoh's shared memory on (its default: payloads over 3 KB go
  through a shared segment, the TCP link carries a reference);
- tcp: the same with shared memory off;
- netns: TCP between two network namespaces joined by a veth pair (needs root and `ip netns`).

Publisher and subscriber are separate processes using octolog.kit.bus.Bus (reliable, congestion control
BLOCK, bounded inbox), as the stages do. Throughput: the publisher sends back to back, the subscriber
times first to last arrival. Latency: one message at a time (the next goes after the subscriber's
ack), one-way = arrival - send on the shared monotonic clock. With `--wire` a second table gives bytes
per frame and encode/decode cost for each wire compression setting (schemas.rgbdmsgs), and the frame
rate over TCP with it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

HEAD = struct.Struct("<cQQ")  # phase, seq, send time (ns, CLOCK_MONOTONIC: one clock per host)
LAT, THR, END = b"L", b"T", b"E"


# --- payloads --------------------------------------------------------------------------------------


def frame_source():
    data = Path(os.environ.get("OCTOLOG_DATA", ROOT.parent / "shared" / "data"))
    folder = data / "tum" / "rgbd_dataset_freiburg1_xyz_first300"
    from octolog.replay.sources import open_source

    spec = f"tum:{folder}" if folder.is_dir() else "synthetic:2"
    return spec, open_source(spec)


def payloads() -> tuple[str, dict[str, bytes]]:
    from octolog.schemas import codec, posemsgs, rgbdmsgs, topics

    spec, src = frame_source()
    frame = next(src.frames(0, 1))
    pose = posemsgs.pose_stamped_msg(np.eye(4), frame.stamp_ns)
    return spec, {"rgbd": codec.encode(rgbdmsgs.rgbd_msg(frame), topics.RGBD.msgtype),
                  "small": codec.encode(pose, topics.POSE.msgtype)}


# --- the two roles (run as subprocesses) -------------------------------------------------------------


def _bus(mode: str, endpoint: str, shm: bool, stage: str):
    from octolog.kit.bus import Bus, BusConfig

    cfg_file = Path(tempfile.mkdtemp()) / "zenoh.json5"
    cfg_file.write_text(json.dumps({"transport": {"shared_memory": {"enabled": shm}}}))
    kw = {"listen": (endpoint,)} if mode == "listen" else {"connect": (endpoint,)}
    return Bus(BusConfig(mode="peer", multicast_scouting=False, zenoh_config=str(cfg_file), **kw), stage,
               inbox_size=8)


def role_sub(endpoint: str, shm: bool) -> None:
    from octolog.schemas.topics import Topic

    data, ack = Topic("bench/data", "std_msgs/msg/String"), Topic("bench/ack", "std_msgs/msg/String")
    lat: list[int] = []
    n_thr, t_first, t_last, nbytes = 0, 0, 0, 0
    with _bus("listen", endpoint, shm, "sub") as bus:
        pub = bus.publisher(ack)
        bus.start([data])
        while True:
            r = bus.receive(timeout_s=30)
            now = time.monotonic_ns()
            if r is None:
                sys.exit("sub: no message for 30 s")
            phase, seq, sent = HEAD.unpack_from(r.payload)
            if phase == LAT:
                lat.append(now - sent)
                pub.put_raw(r.payload[:HEAD.size])
            elif phase == THR:
                t_first = t_first or now
                t_last, n_thr, nbytes = now, n_thr + 1, len(r.payload)
            else:
                pub.put_raw(r.payload[:HEAD.size])
                break
    print(json.dumps({"lat_ns": lat, "n": n_thr, "span_ns": t_last - t_first, "bytes": nbytes}), flush=True)


def role_pub(endpoint: str, shm: bool, payload_file: str, n_lat: int, n_thr: int) -> None:
    from octolog.schemas.topics import Topic

    body = Path(payload_file).read_bytes()
    data, ack = Topic("bench/data", "std_msgs/msg/String"), Topic("bench/ack", "std_msgs/msg/String")
    with _bus("connect", endpoint, shm, "pub") as bus:
        pub = bus.publisher(data)
        bus.start([ack], wait_for=["sub"], timeout_s=60)

        def put(phase: bytes, seq: int) -> None:
            pub.put_raw(HEAD.pack(phase, seq, time.monotonic_ns()) + body)

        def wait_ack() -> None:
            while bus.receive(timeout_s=30) is None:
                pass

        for i in range(n_lat + 10):  # 10 warm-up messages, dropped by the caller
            put(LAT, i)
            wait_ack()
        for i in range(n_thr):
            put(THR, i)
        put(END, 0)
        wait_ack()


# --- orchestration -----------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


class Netns:
    """Two namespaces joined by a veth pair: pub in A (198.18.10.1), sub in B (198.18.10.2)."""

    def __init__(self, rate_mbit: float = 0.0) -> None:
        tag = f"ob{os.getpid() % 100000}"
        self.a, self.b = f"{tag}a", f"{tag}b"
        self.rate_mbit = rate_mbit  # > 0: a token-bucket shaper on both ends (a slower link, e.g. Wi-Fi)

    def __enter__(self) -> Netns:
        _ip("netns", "add", self.a)
        _ip("netns", "add", self.b)
        _ip("link", "add", f"{self.a}0", "type", "veth", "peer", "name", f"{self.b}0")
        _ip("link", "set", f"{self.a}0", "netns", self.a)
        _ip("link", "set", f"{self.b}0", "netns", self.b)
        for ns, addr in ((self.a, "198.18.10.1/24"), (self.b, "198.18.10.2/24")):
            _ip("-n", ns, "addr", "add", addr, "dev", f"{ns}0")
            _ip("-n", ns, "link", "set", f"{ns}0", "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            if self.rate_mbit:
                subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", f"{ns}0", "root", "tbf",
                                "rate", f"{self.rate_mbit}mbit", "burst", "256kb", "latency", "50ms"],
                               check=True, capture_output=True)
        return self

    def __exit__(self, *exc: object) -> None:
        for ns in (self.a, self.b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def netns_reason() -> str | None:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return "needs root and iproute2"
    probe = subprocess.run(["ip", "netns", "add", f"obprobe{os.getpid()}"], capture_output=True, text=True)
    if probe.returncode != 0:
        return f"ip netns not allowed: {probe.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", f"obprobe{os.getpid()}"], capture_output=True)
    return None


def measure(transport: str, body: bytes, n_lat: int, n_thr: int, netns: Netns | None = None) -> dict:
    shm = transport == "shm"
    if netns is not None:
        endpoint = "tcp/198.18.10.2:7447"
        wrap_sub, wrap_pub = ["ip", "netns", "exec", netns.b], ["ip", "netns", "exec", netns.a]
    else:
        endpoint, wrap_sub, wrap_pub = f"tcp/127.0.0.1:{_free_port()}", [], []
    with tempfile.NamedTemporaryFile(suffix=".bin") as f:
        f.write(body)
        f.flush()
        me = [sys.executable, str(Path(__file__).resolve())]
        env = {**os.environ, "PYTHONHASHSEED": "0"}
        sub = subprocess.Popen([*wrap_sub, *me, "--role", "sub", "--endpoint", endpoint, *(["--shm"] if shm else [])],
                               stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
        pub = subprocess.run([*wrap_pub, *me, "--role", "pub", "--endpoint", endpoint, "--payload", f.name,
                              "--n-lat", str(n_lat), "--n-thr", str(n_thr), *(["--shm"] if shm else [])],
                             env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
        out, _ = sub.communicate(timeout=120)
    if pub.returncode != 0 or sub.returncode != 0:
        raise SystemExit(f"bench {transport}: pub {pub.returncode} {pub.stderr[-500:]} / sub {sub.returncode}")
    res = json.loads(out.strip().splitlines()[-1])
    lat = np.array(res["lat_ns"][10:]) / 1e6
    rate = (res["n"] - 1) / (res["span_ns"] * 1e-9) if res["span_ns"] else float("nan")
    return {"msgs_s": rate, "mb_s": rate * res["bytes"] / 1e6, "lat_med_ms": float(np.median(lat)),
            "lat_p99_ms": float(np.percentile(lat, 99))}


def memcpy(body: bytes, n: int, *, fresh: bool = False) -> dict:
    """One copy of the bytes: into a reused buffer (cache-hot), or `fresh`: into a new bytes object,
    as a receiver taking a sample out of Zenoh does."""
    src = np.frombuffer(body, dtype=np.uint8)
    dst = np.empty_like(src)
    times = []
    for _ in range(n + 10):
        t0 = time.perf_counter_ns()
        if fresh:
            bytes(memoryview(body))
        else:
            np.copyto(dst, src)
        times.append(time.perf_counter_ns() - t0)
    t = np.array(times[10:]) / 1e9
    return {"msgs_s": 1 / np.median(t), "mb_s": len(body) / np.median(t) / 1e6,
            "lat_med_ms": float(np.median(t) * 1e3), "lat_p99_ms": float(np.percentile(t, 99) * 1e3)}


def wire_table(n: int, link_mbit: float, netns_ok: bool, n_thr: int) -> list[str]:
    """Bytes per frame and codec cost per wire compression setting, on 640x480 frames, and the frame
    rate through the Bus between two namespaces over a link shaped to `link_mbit`."""
    from octolog.schemas import codec, rgbdmsgs, topics, wirecompression

    spec, src = frame_source()
    frames = list(src.frames(0, n))
    link = f"frames/s over {link_mbit:g} Mbit/s (netns)"
    rows = [f"| wire setting | bytes/frame (mean) | vs raw | encode ms | decode ms | codec-bound frames/s | {link} |",
            "|---|---:|---:|---:|---:|---:|---:|"]
    raw_size = None
    for setting in ("raw", "png,png", "jpeg:95,png", "jpeg:90,png", "jpeg:75,png"):
        wire = wirecompression.parse_wire_compression(setting)
        sizes, enc, dec, sample = [], [], [], b""
        for f in frames:
            t0 = time.perf_counter()
            msg = rgbdmsgs.rgbd_msg(f) if wire is None else rgbdmsgs.compressed_rgbd_msg(f, wire)
            topic = topics.RGBD if wire is None else topics.RGBD_COMPRESSED
            data = codec.encode(msg, topic.msgtype)
            t1 = time.perf_counter()
            rgbdmsgs.rgbd_from_msg(codec.decode(data, topic.msgtype))
            t2 = time.perf_counter()
            sizes.append(len(data))
            sample = sample or data
            enc.append((t1 - t0) * 1e3)
            dec.append((t2 - t1) * 1e3)
        size = float(np.mean(sizes))
        raw_size = raw_size or size
        e, d = float(np.median(enc)), float(np.median(dec))
        over_link = "skipped (no netns)"
        if netns_ok:
            with Netns(link_mbit) as ns:
                over_link = f"{measure('tcp', sample, 5, n_thr, ns)['msgs_s']:.1f}"
        rows.append(f"| {setting} | {size:,.0f} | {size / raw_size:.2f} | {e:.1f} | {d:.1f} | {1000 / max(e, d):.0f} "
                    f"| {over_link} |")
    return [f"Frames: {spec}, first {n}, 640x480; encode = build + compress + CDR, decode = CDR + decompress "
            f"(one process, medians); the link column sends frame 0's message {n_thr} times through the Bus "
            f"between two namespaces with `tc tbf rate {link_mbit:g}mbit` on the veth pair", "", *rows]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--role", choices=("pub", "sub"))
    ap.add_argument("--endpoint")
    ap.add_argument("--payload")
    ap.add_argument("--shm", action="store_true")
    ap.add_argument("--n-lat", type=int, default=0)
    ap.add_argument("--n-thr", type=int, default=0)
    ap.add_argument("--frames", type=int, default=200, help="RGB-D frames per throughput run")
    ap.add_argument("--small", type=int, default=20000, help="small messages per throughput run")
    ap.add_argument("--latency", type=int, default=300, help="messages per latency run")
    ap.add_argument("--wire", action="store_true", help="also the wire-compression table")
    ap.add_argument("--link-mbit", type=float, default=100.0, help="--wire: shaped link rate (default 100)")
    args = ap.parse_args()
    if args.role == "sub":
        return role_sub(args.endpoint, args.shm)
    if args.role == "pub":
        return role_pub(args.endpoint, args.shm, args.payload, args.n_lat, args.n_thr)

    spec, bodies = payloads()
    reason = netns_reason()
    rows = []
    for kind, body in bodies.items():
        n_thr = args.frames if kind == "rgbd" else args.small
        results = {"memcpy (reused buffer)": memcpy(body, max(args.latency, 1000)),
                   "memcpy (new bytes)": memcpy(body, max(args.latency, 1000), fresh=True)}
        for transport in ("shm", "tcp"):
            results[transport] = measure(transport, body, args.latency, n_thr)
        if reason is None:
            with Netns() as ns:
                results["netns tcp"] = measure("tcp", body, args.latency, n_thr, ns)
        for transport, r in results.items():
            rows.append(f"| {kind} ({len(body):,} B) | {transport} | {r['msgs_s']:,.0f} | {r['mb_s']:,.0f} | "
                        f"{r['lat_med_ms']:.3f} | {r['lat_p99_ms']:.3f} |")
    print(f"# bench/transport.py on {platform.node()} ({os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}), "
          f"Python {platform.python_version()}, eclipse-zenoh {_version('eclipse-zenoh')}")
    print(f"Payload frame: {spec} frame 0 as CDR RgbdFrame; small: PoseStamped CDR. Throughput: {args.frames} "
          f"frames / {args.small} small messages back to back; latency: {args.latency} paced messages.")
    if reason is not None:
        print(f"netns: skipped ({reason})")
    print()
    print("| payload | transport | msgs/s | MB/s | latency median ms | latency p99 ms |")
    print("|---|---|---:|---:|---:|---:|")
    print("\n".join(rows))
    if args.wire:
        print()
        print("\n".join(wire_table(30, args.link_mbit, reason is None, max(10, args.frames // 5))))


def _version(name: str) -> str:
    from importlib.metadata import version

    return version(name)


if __name__ == "__main__":
    main()
