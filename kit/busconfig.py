"""Transport settings shared by every stage: `BusConfig`.

Apart from `octolog.kit.bus` (which re-exports it) so that the command line can build and validate
one while it parses its arguments without importing Zenoh or the message codec (numpy, scipy,
rosbags): `octolog eval`, `info` and `--help` do not pay for a transport they never open.
"""

from __future__ import annotations

from dataclasses import dataclass

from octolog.kit.errors import BusError


@dataclass(frozen=True)
class BusConfig:
    """Transport settings shared by every stage (see `octolog <cmd> --help`)."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    namespace: str = ""
    zenoh_config: str | None = None
    multicast_scouting: bool = True
    # samples each publisher keeps (at most HISTORY_MB of them) so that subscribers can recover
    # what a cut link lost and late joiners get the recent past; 0: plain pub/sub, no recovery
    history: int = 32
    # the streams that `keeps_all` (keyframes) keep every sample up to this many MB per publisher
    keep_mb: int = 2048
    # samples held behind a gap (waiting for a publisher's history to fill it), over every
    # publisher, at most this many MB: past it the publisher holding most is refused and the stage ends
    max_held_mb: int = 512
    # how long a vanished peer stage may stay away (a cut link) before it counts as dead
    peer_timeout_s: float = 30.0
    # also publish every standard-typed topic the way ROS 2's rmw_zenoh does, in this ROS domain
    # (octolog.kit.bus.ros2); -1: off
    ros2_domain: int = -1

    def validate(self) -> None:
        """Raise BusError naming the flag if a value cannot work (the CLI calls this once)."""
        if self.mode not in ("peer", "client", "router"):
            raise BusError(f"--mode {self.mode!r}: want peer, client or router")
        if self.history < 0 or self.keep_mb < 0 or self.peer_timeout_s <= 0 or self.max_held_mb <= 0:
            raise BusError("bus history and keep_mb must be >= 0, peer_timeout_s and max_held_mb > 0")
        if not -1 <= self.ros2_domain <= 232:  # ROS 2 domain ids: 0-232 (rmw's bound)
            raise BusError(f"--ros2-domain {self.ros2_domain}: want a ROS domain id 0-232 (or -1: off)")
