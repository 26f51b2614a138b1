"""TLS with mutual authentication and access control, configured through Zenoh config files.

The router is `octolog router` in its own process with docs/examples/zenoh-tls-router.json5; the
certificates come from docs/examples/make-certs.sh (openssl), so the documented example is what
runs here. Clients are real Zenoh sessions (octolog.kit.bus.Bus) with docs/examples/zenoh-tls-client.json5
pointed at their own certificates.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from helpers import ROOT, octolog

from octolog.kit.bus import Bus, BusConfig
from octolog.kit.errors import BusError
from octolog.schemas import codec
from octolog.schemas.topics import RGBD, Topic

EXAMPLES = ROOT / "docs" / "examples"
N = 20
FENCE = Topic("mapper/end", "octolog_msgs/msg/StreamEnd")  # allowed to viewers: marks the end of the data


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl not installed")
    tmp = tmp_path_factory.mktemp("tls")
    subprocess.run(["bash", str(EXAMPLES / "make-certs.sh"), str(tmp / "certs")], check=True, capture_output=True)
    # a second, unrelated authority issuing a certificate with an allowed name
    subprocess.run(["bash", str(EXAMPLES / "make-certs.sh"), str(tmp / "rogue")], check=True, capture_output=True,
                   env={**os.environ, "NODES": "robot1"})
    return tmp


def _config(pki: Path, example: str, name: str, *, cert: str | None = None, ca: str = "certs",
            extra: str = "") -> str:
    """The example config with absolute certificate paths for node `cert` (None: no certificate)."""
    text = (EXAMPLES / example).read_text().replace('"certs/', f'"{pki}/certs/')
    if cert is not None:
        text = text.replace(f'{pki}/certs/robot1.', f'{pki}/{ca}/{cert}.')
    else:
        text = "\n".join(ln for ln in text.splitlines() if "connect_certificate" not in ln
                         and "connect_private_key" not in ln)
    text = text.replace(f'"{pki}/certs/ca.pem"', f'"{pki}/{ca}/ca.pem"')
    if extra:
        text = text.rstrip().rstrip("}") + extra + "\n}\n"
    path = pki / f"{name}.json5"
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module")
def router(pki):
    endpoint = f"tls/localhost:{_free_port()}"
    cfg = _config(pki, "zenoh-tls-router.json5", "router")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "octolog", "router", "--zenoh-config", cfg, "--listen", endpoint],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    line = proc.stdout.readline()
    assert "router: listening on" in line, line + proc.stdout.read()
    # the line comes once the router's session is open; a certified client getting a session as well
    # says TLS works, so the refusals below are refusals, not a router still starting
    with _bus(endpoint, _config(pki, "zenoh-tls-client.json5", "probe", cert="server"), "probe"):
        pass
    yield endpoint
    proc.terminate()
    proc.wait(timeout=30)


def _bus(endpoint: str, config: str, stage: str) -> Bus:
    return Bus(BusConfig(mode="client", connect=(endpoint,), zenoh_config=config, multicast_scouting=False,
                         namespace="robot1"), stage)


class Counter:
    """Counts samples per topic; `hello` is set by the first fence message, `done` by the one with count N."""

    def __init__(self, bus: Bus, topics: list[Topic]) -> None:
        import zenoh

        self.counts: dict[str, int] = {}
        self.hello, self.done = threading.Event(), threading.Event()
        self.subscribers = []  # kept alive as long as the counter
        for t in topics:  # declared in this order on one link: the router handles them in this order
            def on(sample, t=t) -> None:
                self.counts[t.name] = self.counts.get(t.name, 0) + 1
                if t == FENCE:
                    self.hello.set()
                    if codec.decode(sample.payload.to_bytes(), FENCE.msgtype).count == N:
                        self.done.set()

            self.subscribers.append(bus.session.declare_subscriber(t.key("robot1"), zenoh.handlers.Callback(on)))


def test_certified_nodes_join_and_access_control_limits_what_they_get(pki, router):
    """robot1 publishes camera frames, then an end message on a map key; the server (allowed on
    robot1/**) gets all of them; a viewer (allowed on robot1/mapper/** only) gets the end message but
    no camera frame."""
    import numpy as np

    from octolog.kit.geometry import Intrinsics, RgbdFrame

    server_cfg = _config(pki, "zenoh-tls-client.json5", "server", cert="server")
    viewer_cfg = _config(pki, "zenoh-tls-client.json5", "viewer", cert="viewer")
    robot_cfg = _config(pki, "zenoh-tls-client.json5", "robot1", cert="robot1")
    with _bus(router, server_cfg, "mapper") as server, _bus(router, viewer_cfg, "viewer") as viewer, \
            _bus(router, robot_cfg, "replay") as robot:
        got_server = Counter(server, [RGBD, FENCE])
        got_viewer = Counter(viewer, [RGBD, FENCE])  # the camera subscription goes first
        pub, fence = robot.publisher(RGBD), robot.publisher(FENCE)
        # until both have seen a fence, their subscriptions may not have reached the router yet;
        # once they have, the camera subscriptions (declared before) are in place too
        while not (got_server.hello.wait(0.2) and got_viewer.hello.wait(0.2)):
            fence.put(codec.stream_end_msg(RGBD.name, 0))
        hellos = fence.count
        frame = RgbdFrame(0, 1, np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.uint16), 0.001,
                          Intrinsics(4, 4, 2.0, 2.0, 2.0, 2.0))
        for _ in range(N):
            pub.put(codec.rgbd_msg(frame))
        fence.put(codec.stream_end_msg(RGBD.name, N))
        assert got_server.done.wait(60) and got_viewer.done.wait(60)
    assert got_server.counts[RGBD.name] == N
    # the end message went through the same router link after the frames: had the viewer been
    # allowed the frames, they would be here before it
    assert RGBD.name not in got_viewer.counts
    assert got_viewer.counts[FENCE.name] <= hellos + 1 and got_server.counts[FENCE.name] <= hellos + 1


def test_a_client_without_a_certificate_is_refused(pki, router):
    cfg = _config(pki, "zenoh-tls-client.json5", "nocert", extra='  connect: { timeout_ms: 3000 },')
    proc = octolog("track", "--mode", "client", "--connect", router, "--zenoh-config", cfg, "--no-multicast",
                   "--namespace", "robot1", check=False, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1 and "octolog track: error: cannot open Zenoh session (client)" in proc.stderr


def test_a_certificate_from_another_authority_is_refused(pki, router):
    """A robot1 certificate signed by another CA: the router refuses the handshake (and the client,
    trusting only its own CA, refuses the router's certificate)."""
    cfg = _config(pki, "zenoh-tls-client.json5", "rogue", cert="robot1", ca="rogue",
                  extra='  connect: { timeout_ms: 3000 },')
    with pytest.raises(BusError, match="cannot open Zenoh session"):
        with _bus(router, cfg, "replay"):
            pass


def test_plain_tcp_is_not_accepted(pki, router):
    """The router only speaks TLS: a plain tcp client to the same port never gets a session."""
    port = router.rsplit(":", 1)[1]
    cfg = pki / "plain.json5"
    cfg.write_text("{ connect: { timeout_ms: 3000 } }")
    with pytest.raises(BusError, match="cannot open Zenoh session"):
        with _bus(f"tcp/127.0.0.1:{port}", str(cfg), "replay"):
            pass


@pytest.mark.parametrize("history_rule", [True, False], ids=["history-allowed", "history-denied"])
def test_a_late_joiner_recovers_the_history_only_where_access_control_allows_it(pki, history_rule, tmp_path):
    """robot1 publishes 5 frames before the server subscribes; the server's Bus recovers them from
    the publisher's history (`<key>/@history/<id>` queries), which the router's rules must allow
    beside `robot1/**`. With the history rule removed, nothing is recovered."""
    import numpy as np

    from octolog.kit.geometry import Intrinsics, RgbdFrame

    text = (EXAMPLES / "zenoh-tls-router.json5").read_text().replace('"certs/', f'"{pki}/certs/')
    if not history_rule:
        text = text.replace('"robot1/**", "robot1/**/@history/*"', '"robot1/**"')
    (tmp_path / "router.json5").write_text(text)
    endpoint = f"tls/localhost:{_free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "octolog", "router", "--zenoh-config", str(tmp_path / "router.json5"),
                             "--listen", endpoint], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        assert "router: listening on" in proc.stdout.readline()
        robot_cfg = _config(pki, "zenoh-tls-client.json5", "robot1", cert="robot1")
        server_cfg = _config(pki, "zenoh-tls-client.json5", "server", cert="server")
        frame = RgbdFrame(0, 1, np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.uint16), 0.001,
                          Intrinsics(4, 4, 2.0, 2.0, 2.0, 2.0))
        with _bus(endpoint, robot_cfg, "replay") as robot:
            pub = robot.publisher(RGBD)
            for _ in range(5):
                pub.put(codec.rgbd_msg(frame))
            with _bus(endpoint, server_cfg, "mapper") as late:
                late.subscribe([RGBD])
                got = 0
                # recovery asks the histories at once and then every second while idle: 5 s is plenty
                for _ in range(20 if history_rule else 8):
                    while late.receive(timeout_s=0.25 if got < 5 else 0.0) is not None:
                        got += 1
                    if got == 5:
                        break
        assert got == (5 if history_rule else 0)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
