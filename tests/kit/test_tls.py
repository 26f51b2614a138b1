"""TLS with mutual authentication and access control, configured through Zenoh config files.

The router is `octolog router` in its own process with docs/examples/zenoh-tls-router.json5; the
certificates come from docs/examples/make-certs.sh (openssl), so the documented example is what
runs here. Clients are real Zenoh sessions (octolog.kit.bus.Bus) with docs/examples/zenoh-tls-client.json5
pointed at their own certificates.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh
from helpers import ROOT, free_port, octolog

from octolog.kit.bus import Bus, BusConfig
from octolog.kit.errors import BusError
from octolog.schemas import codec, rgbdmsgs, streammsgs
from octolog.schemas.topics import MAP_UPDATE, RGBD, Topic

EXAMPLES = ROOT / "docs" / "examples"
N = 20
FENCE = Topic("mapper/end", "octolog_msgs/msg/StreamEnd")  # allowed to viewers: marks the end of the data
BLOCK = zenoh.CongestionControl.BLOCK  # every sample sent arrives, or is refused: none dropped for speed



@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl not installed")
    tmp = tmp_path_factory.mktemp("tls")
    subprocess.run(["bash", str(EXAMPLES / "make-certs.sh"), str(tmp / "certs")], check=True, capture_output=True)
    # a second, unrelated authority issuing a certificate with an allowed name
    subprocess.run(["bash", str(EXAMPLES / "make-certs.sh"), str(tmp / "rogue")], check=True, capture_output=True,
                   env={**os.environ, "NODES": "robot1"})
    _expired(tmp / "certs", "robot1-expired", "robot1")
    return tmp


def _expired(certs: Path, name: str, cn: str) -> None:
    """A certificate for CN `cn` from the real CA, valid for one day in 2020 (`openssl ca` sets dates)."""
    (certs / "index.txt").write_text("")
    (certs / "ca.cnf").write_text(f"""[ca]\ndefault_ca = ca_default\n[ca_default]\ndatabase = {certs}/index.txt
new_certs_dir = {certs}\nserial = {certs}/ca.srl\ndefault_md = sha256\npolicy = any\n[any]\ncommonName = supplied\n""")
    (certs / f"{name}.ext").write_text("basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n"
                                       "extendedKeyUsage=clientAuth\n")
    run = lambda *a: subprocess.run(a, check=True, capture_output=True, cwd=certs)  # noqa: E731
    run("openssl", "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", f"{name}.key")
    run("openssl", "req", "-new", "-key", f"{name}.key", "-subj", f"/CN={cn}", "-out", f"{name}.csr")
    run("openssl", "ca", "-batch", "-config", "ca.cnf", "-cert", "ca.pem", "-keyfile", "ca.key", "-in", f"{name}.csr",
        "-out", f"{name}.pem", "-notext", "-startdate", "20200101000000Z", "-enddate", "20200102000000Z",
        "-extfile", f"{name}.ext")


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
    endpoint = f"tls/localhost:{free_port()}"
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
        self.changed = threading.Condition()
        self.subscribers = []  # kept alive as long as the counter
        for t in topics:  # declared in this order on one link: the router handles them in this order
            def on(sample, t=t) -> None:
                with self.changed:
                    self.counts[t.name] = self.counts.get(t.name, 0) + 1
                    self.changed.notify_all()
                if t == FENCE:
                    self.hello.set()
                    if codec.decode(sample.payload.to_bytes(), FENCE.msgtype).count == N:
                        self.done.set()

            self.subscribers.append(bus.session.declare_subscriber(t.key("robot1"), zenoh.handlers.Callback(on)))

    def wait(self, predicate, timeout_s: float = 60.0) -> bool:
        with self.changed:
            return self.changed.wait_for(predicate, timeout_s)


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
            fence.put(streammsgs.stream_end_msg(RGBD.name, 0))
        hellos = fence.count
        frame = RgbdFrame(0, 1, np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.uint16), 0.001,
                          Intrinsics(4, 4, 2.0, 2.0, 2.0, 2.0))
        for _ in range(N):
            pub.put(rgbdmsgs.rgbd_msg(frame))
        fence.put(streammsgs.stream_end_msg(RGBD.name, N))
        assert got_server.done.wait(60) and got_viewer.done.wait(60)
    assert got_server.counts[RGBD.name] == N
    # the end message went through the same router link after the frames: had the viewer been
    # allowed the frames, they would be here before it
    assert RGBD.name not in got_viewer.counts
    assert got_viewer.counts[FENCE.name] <= hellos + 1 and got_server.counts[FENCE.name] <= hellos + 1


# --- refusals at the door: each client first connects to a router that does not ask for what it lacks ---

def _router_config(pki: Path, name: str, *, mtls: bool = True, trust: str = "certs", tls: bool = True) -> str:
    """The example router's config (or a plain one), asking for a client certificate or not, trusting
    the CA in folder `trust`."""
    if tls:
        text = (EXAMPLES / "zenoh-tls-router.json5").read_text().replace('"certs/', f'"{pki}/certs/')
        text = text.replace(f'"{pki}/certs/ca.pem"', f'"{pki}/{trust}/ca.pem"')
        if not mtls:
            text = text.replace("enable_mtls: true", "enable_mtls: false")
    else:
        text = '{ mode: "router" }'
    path = pki / f"{name}.json5"
    path.write_text(text)
    return str(path)


@contextmanager
def _router(config: str, scheme: str = "tls"):
    endpoint = f"{scheme}/localhost:{free_port()}" if scheme == "tls" else f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "octolog", "router", "--zenoh-config", config, "--listen", endpoint],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stdout.readline()
        assert "router: listening on" in line, line + proc.stdout.read()
        yield endpoint
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def _connects(endpoint: str, config: str) -> bool:
    return _refusal(endpoint, config) is None


def _refusal(endpoint: str, config: str) -> str | None:
    """None if the client gets a session, else the bus's one-line error."""
    try:
        with _bus(endpoint, config, "replay"):
            return None
    except BusError as exc:
        assert "cannot open Zenoh session" in str(exc)
        return str(exc)


QUICK = "  connect: { timeout_ms: 3000 },"


def test_a_client_without_a_certificate_is_refused_by_the_router(pki, router):
    """The client trusts the real CA and does not insist on mutual TLS: it connects to a router that
    asks for no client certificate, and the real router refuses it (the refusal is the router's)."""
    cfg = _config(pki, "zenoh-tls-client.json5", "nocert", extra=QUICK)
    Path(cfg).write_text(Path(cfg).read_text().replace("enable_mtls: true", "enable_mtls: false"))
    with _router(_router_config(pki, "router-no-mtls", mtls=False)) as lenient:
        assert _connects(lenient, cfg)
    assert "the router refused this node's certificate (tlsv13 alert certificate required)" in _refusal(router, cfg)
    # and as a user meets it: one line from the stage
    proc = octolog("track", "--mode", "client", "--connect", router, "--zenoh-config", cfg, "--no-multicast",
                   "--namespace", "robot1", check=False, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1 and "octolog track: error: cannot open Zenoh session (client)" in proc.stderr


@pytest.mark.slow
def test_a_certificate_from_another_authority_is_refused_by_the_router(pki, router):
    """A robot1 certificate signed by another CA, the client trusting the real CA (so it accepts the
    router's certificate): a router that trusts the other CA lets it in, the real router refuses it."""
    cfg = _config(pki, "zenoh-tls-client.json5", "rogue", cert="robot1", ca="rogue", extra=QUICK)
    Path(cfg).write_text(Path(cfg).read_text().replace(f'"{pki}/rogue/ca.pem"', f'"{pki}/certs/ca.pem"'))
    with _router(_router_config(pki, "router-trusts-rogue", trust="rogue")) as other:
        assert _connects(other, cfg)
    # rustls answers a certificate whose issuer has the right name but the wrong key with "decrypt
    # error", one from an unknown issuer name with "unknown ca": either way, a refusal
    assert "the router refused this node's certificate (tlsv1 alert" in _refusal(router, cfg)
    # and the other way round: a node that trusts only the other CA does not trust the router
    cfg = _config(pki, "zenoh-tls-client.json5", "rogue-trust", cert="robot1", ca="rogue", extra=QUICK)
    assert "this node does not trust the router's certificate (unable to get local issuer certificate)" in \
        _refusal(router, cfg)


def test_an_expired_certificate_is_refused_by_the_router(pki, router):
    """robot1's certificate from the real CA, valid in 2020 only: a router that checks no client
    certificate lets the client in, the real router refuses it; the same client with a current
    certificate is let in (nothing else about it is wrong)."""
    cfg = _config(pki, "zenoh-tls-client.json5", "expired", cert="robot1-expired", extra=QUICK)
    with _router(_router_config(pki, "router-no-mtls-2", mtls=False)) as lenient:
        assert _connects(lenient, cfg)
    assert "the router refused this node's certificate (sslv3 alert certificate expired)" in _refusal(router, cfg)
    assert _connects(router, _config(pki, "zenoh-tls-client.json5", "current", cert="robot1", extra=QUICK))


def test_plain_tcp_is_refused_by_the_router(pki, router):
    """A plain tcp client connects to a plain router; to the TLS router's port it never gets a session."""
    cfg = pki / "plain.json5"
    cfg.write_text("{ connect: { timeout_ms: 3000 } }")
    with _router(_router_config(pki, "router-plain", tls=False), scheme="tcp") as plain:
        assert _connects(plain, str(cfg))
    port = router.rsplit(":", 1)[1]
    assert "the port accepts TCP but no Zenoh session opened (a TLS-only router there?" in \
        _refusal(f"tcp/127.0.0.1:{port}", str(cfg))


def test_a_router_that_is_not_there_is_told_from_a_refused_certificate(pki, router):
    """Nothing listening, a name that does not resolve: each says so, unlike a refusal above."""
    cfg = _config(pki, "zenoh-tls-client.json5", "robot1-quick", cert="robot1", extra=QUICK)
    port = free_port()
    assert f"tls/localhost:{port}: connection refused" in _refusal(f"tls/localhost:{port}", cfg)
    assert "cannot resolve 'no-such-host.invalid'" in _refusal("tls/no-such-host.invalid:7447", cfg)


# --- what certified nodes may do once in -------------------------------------------------------------

def _hello(counter: Counter, bus: Bus, fence: Topic = FENCE) -> None:
    """Until `counter` has seen a fence, its subscriptions may not have reached the router yet."""
    pub = bus.publisher(fence)
    while not counter.hello.wait(0.2):
        pub.put(streammsgs.stream_end_msg(RGBD.name, 0))


def test_a_viewer_cannot_publish_anything(pki, router):
    """The viewer puts camera frames and map updates; the server, subscribed to both, gets none of
    them, though the viewer's map query sent after them on the same link reaches it and is answered.
    robot1 sending the same gets them through (the positive control)."""
    server_cfg = _config(pki, "zenoh-tls-client.json5", "server", cert="server")
    viewer_cfg = _config(pki, "zenoh-tls-client.json5", "viewer", cert="viewer")
    robot_cfg = _config(pki, "zenoh-tls-client.json5", "robot1", cert="robot1")
    with _bus(router, server_cfg, "mapper") as server, _bus(router, viewer_cfg, "viewer") as viewer, \
            _bus(router, robot_cfg, "replay") as robot:
        got = Counter(server, [RGBD, MAP_UPDATE, FENCE])
        asked = threading.Event()
        server.session.declare_queryable("robot1/mapper/probe", lambda q: (asked.set(), q.reply(q.key_expr, b"ok")))
        _hello(got, robot)
        payload = codec.encode(streammsgs.stream_end_msg("x", 1), FENCE.msgtype)
        for _ in range(N):
            viewer.session.put(RGBD.key("robot1"), payload, congestion_control=BLOCK)
            viewer.session.put(MAP_UPDATE.key("robot1"), payload, congestion_control=BLOCK)
        replies = [r for r in viewer.session.get("robot1/mapper/probe", timeout=30) if r.ok is not None]
        assert asked.is_set() and len(replies) == 1  # after the puts, on the same link
        assert RGBD.name not in got.counts and MAP_UPDATE.name not in got.counts
        for _ in range(N):  # control: robot1 may
            robot.session.put(RGBD.key("robot1"), payload, congestion_control=BLOCK)
            robot.session.put(MAP_UPDATE.key("robot1"), payload, congestion_control=BLOCK)
        robot.publisher(FENCE).put(streammsgs.stream_end_msg(RGBD.name, N))
        assert got.done.wait(60)
    assert got.counts[RGBD.name] == N and got.counts[MAP_UPDATE.name] == N


def test_a_robot_cannot_write_into_or_read_from_another_robots_namespace(pki, router):
    """robot2 puts frames on robot1's camera key, then on its own: the server (allowed both) gets
    robot2's own frames and none on robot1's key. robot1's frames reach the server but not robot2,
    subscribed to them (its listening session): the server's next message to it arrives, they never do.
    Every put is BLOCK: Zenoh may let a DROP sample overtake BLOCK ones."""
    server_cfg = _config(pki, "zenoh-tls-client.json5", "server", cert="server")
    r1_cfg = _config(pki, "zenoh-tls-client.json5", "robot1", cert="robot1")
    r2_cfg = _config(pki, "zenoh-tls-client.json5", "robot2", cert="robot2")
    with _bus(router, server_cfg, "mapper") as server, _bus(router, r1_cfg, "replay") as robot1, \
            _bus(router, r2_cfg, "replay") as robot2, _bus(router, r2_cfg, "mapper") as robot2_listener:
        frame = codec.encode(streammsgs.stream_end_msg("frame", 0), FENCE.msgtype)
        got, got2 = Counter(server, [RGBD, FENCE]), _Keys(server, ["robot2/camera/rgbd", "robot2/fence"])
        stolen = _Keys(robot2_listener, ["robot1/camera/rgbd", "robot2/server-fence"])
        _hello(got, robot1)
        while not (got2.wait(lambda: got2.seen("robot2/fence"), 0.2) and
                   stolen.wait(lambda: stolen.seen("robot2/server-fence"), 0.2)):
            robot2.session.put("robot2/fence", frame, congestion_control=BLOCK)
            server.session.put("robot2/server-fence", frame, congestion_control=BLOCK)
        # robot2 into robot1's namespace, then into its own, then its fence
        for _ in range(N):
            robot2.session.put("robot1/camera/rgbd", frame, congestion_control=BLOCK)
        for _ in range(N):
            robot2.session.put("robot2/camera/rgbd", frame, congestion_control=BLOCK)
        # on a link where the router has just refused samples, Zenoh 1.10 can deliver a later one
        # first (a fence overtook robot2's own frames in CI): wait for all of them instead
        assert got2.wait(lambda: got2.count("robot2/camera/rgbd") == N)
        assert RGBD.name not in got.counts
        # robot1's frames: to the server, not to robot2
        for _ in range(N):
            robot1.session.put("robot1/camera/rgbd", frame, congestion_control=BLOCK)
        # the same reordering on robot1's link (CI: the fence came after 7 of its 20 frames): all of them
        assert got.wait(lambda: got.counts.get(RGBD.name, 0) == N)
        before = stolen.count("robot2/server-fence")
        server.session.put("robot2/server-fence", frame, congestion_control=BLOCK)  # after the server had all of robot1's frames
        assert stolen.wait(lambda: stolen.count("robot2/server-fence") > before)
        assert stolen.count("robot1/camera/rgbd") == 0


def test_history_queries_outside_ones_rights_get_nothing(pki, router):
    """robot1 serves a history on robot1/camera/rgbd/@history/...: the server's query is answered;
    the viewer's and robot2's queries never reach it and get no reply."""
    robot_cfg = _config(pki, "zenoh-tls-client.json5", "robot1", cert="robot1")
    asks = {name: _config(pki, "zenoh-tls-client.json5", name, cert=name) for name in ("server", "viewer", "robot2")}
    with _bus(router, robot_cfg, "replay") as robot:
        queries: list[str] = []
        robot.session.declare_queryable("robot1/camera/rgbd/@history/probe",
                                        lambda q: (queries.append("q"), q.reply(q.key_expr, b"history")))
        replies = {}
        for name, cfg in asks.items():  # the server first: its answer shows the queryable is known
            with _bus(router, cfg, "mapper") as asker:
                replies[name] = [r for r in asker.session.get("robot1/camera/rgbd/@history/*", timeout=5)
                                 if r.ok is not None]
    assert len(replies["server"]) == 1 and replies["viewer"] == [] and replies["robot2"] == []
    assert queries == ["q"]


class _Keys:
    """Counts raw samples per key expression (any payload), and signals each arrival."""

    def __init__(self, bus: Bus, keys: list[str]) -> None:
        import zenoh

        self.counts: dict[str, int] = {}
        self.changed = threading.Condition()
        self.subscribers = []
        for key in keys:
            def on(sample, key=key) -> None:
                with self.changed:
                    self.counts[key] = self.counts.get(key, 0) + 1
                    self.changed.notify_all()

            self.subscribers.append(bus.session.declare_subscriber(key, zenoh.handlers.Callback(on)))

    def count(self, key: str) -> int:
        with self.changed:
            return self.counts.get(key, 0)

    def seen(self, key: str) -> bool:
        return self.count(key) > 0

    def wait(self, predicate, timeout_s: float = 60.0) -> bool:
        with self.changed:
            return self.changed.wait_for(predicate, timeout_s)


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
    endpoint = f"tls/localhost:{free_port()}"
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
                pub.put(rgbdmsgs.rgbd_msg(frame))
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
