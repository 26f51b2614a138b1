"""Why a client could not reach its router, when Zenoh only says "Unable to connect ... Timeout!".

Zenoh 1.x reports a refused TLS certificate and a host that does not answer with the same message,
after its connect timeout. After such a failure the bus tries each `connect` endpoint itself: a
plain TCP connection (name resolution, refused, unreachable, no answer), then, for `tls/`, a TLS
handshake with the node's own certificate files from its Zenoh config. The first thing that fails
names the problem: a router that refuses the client's certificate answers the handshake with an
alert ("unknown ca", "certificate expired", "certificate required"), a router whose certificate
the client does not trust fails the client's verification. Other protocols are not probed.
"""

from __future__ import annotations

import json
import socket
import ssl
from typing import Any, Protocol

PROBE_S = 3.0


class ZenohConfig(Protocol):
    """What the probes read of a `zenoh.Config` (only session.py imports zenoh, and it imports this module)."""

    def get_json(self, key: str) -> str: ...


def _tls_setting(zc: ZenohConfig, name: str) -> Any:  # Any: a JSON value
    try:
        return json.loads(zc.get_json(f"transport/link/tls/{name}"))
    except Exception:  # a key the config does not have; zenoh raises its own error type
        return None


def endpoints(zc: ZenohConfig) -> list[str]:
    try:
        return [str(e) for e in json.loads(zc.get_json("connect/endpoints")) or []]
    except Exception:
        return []


def tcp_address(endpoint: str) -> tuple[str, str, int] | None:
    """(protocol, host, port) of a `tcp/` or `tls/` Zenoh endpoint (`tls/[::1]:7447#iface=lo`);
    None for other protocols and malformed ones, which only Zenoh itself can judge."""
    proto, _, addr = endpoint.partition("/")
    host, _, port = addr.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    host = host.strip("[]")
    if proto not in ("tcp", "tls") or not host or not port.isdigit():
        return None
    return proto, host, int(port)


def probe(endpoint: str, zc: ZenohConfig, timeout_s: float = PROBE_S) -> str:
    """What connecting to `endpoint` runs into, in a few words (empty when nothing is wrong that
    this probe can see)."""
    address = tcp_address(endpoint)
    if address is None:
        return ""
    proto, host, port = address
    addr = f"{host}:{port}" if ":" not in host else f"[{host}]:{port}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except socket.gaierror as exc:
        return f"{endpoint}: cannot resolve {host!r} ({exc.strerror})"
    except ConnectionRefusedError:
        return f"{endpoint}: connection refused (the host answers; nothing listens on port {port})"
    except TimeoutError:
        return f"{endpoint}: no answer from {host} within {timeout_s:.0f} s (host down, unreachable, or firewalled)"
    except OSError as exc:
        return f"{endpoint}: unreachable ({exc.strerror or exc})"
    with sock:
        if proto == "tcp":
            return (f"{endpoint}: the port accepts TCP but no Zenoh session opened "
                    f"(a TLS-only router there? try tls/{addr})")
        return _tls_probe(endpoint, sock, host, zc, timeout_s)


def _tls_probe(endpoint: str, sock: socket.socket, host: str, zc: ZenohConfig, timeout_s: float) -> str:
    ca, cert, key = (_tls_setting(zc, k) for k in ("root_ca_certificate", "connect_certificate", "connect_private_key"))
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = bool(_tls_setting(zc, "verify_name_on_connect") in (None, True))
    try:
        if ca:
            ctx.load_verify_locations(ca)
        else:
            ctx.load_default_certs()
        if cert and key and _tls_setting(zc, "enable_mtls"):
            ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        return f"{endpoint}: this node's TLS files do not load ({exc})"
    try:
        with ctx.wrap_socket(sock, server_hostname=host) as tls:
            tls.settimeout(timeout_s)
            # TLS 1.3: the router judges the client's certificate after the handshake; a refusal
            # arrives as an alert on the first read. A router that accepted waits for Zenoh's hello.
            tls.recv(1)
    except ssl.SSLCertVerificationError as exc:
        return f"{endpoint}: this node does not trust the router's certificate ({exc.verify_message})"
    except ssl.SSLError as exc:
        reason = (exc.reason or str(exc)).lower().replace("_", " ")
        if "alert" in reason:
            return f"{endpoint}: the router refused this node's certificate ({reason})"
        return f"{endpoint}: TLS failed ({reason})"
    except TimeoutError:
        return ""  # the handshake passed and the router waits: the refusal, if any, is not TLS's
    except OSError as exc:
        return f"{endpoint}: the router closed the TLS connection ({exc.strerror or exc}): it refused this node"
    return ""


def diagnosis(zc: ZenohConfig) -> str:
    """'; '-joined findings for every connect endpoint of a Zenoh config (empty if none found)."""
    found = [p for p in (probe(e, zc) for e in endpoints(zc)) if p]
    return "; ".join(found)
