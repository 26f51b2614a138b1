"""The Zenoh transport: how stages talk. Import from here; the modules are its parts.

Pipeline topics are reliable with congestion control BLOCK; subscribers feed one bounded inbox per
stage, so a slow consumer slows its producers and nothing is dropped. Stages announce themselves
with liveliness tokens: a producer waits until its consumers are ready, and every stage notices
when a peer stage disappears (process died, link cut) instead of waiting forever.

Loss-free across link failures and restarts (docs/architecture.md, "Bus"): every publisher numbers
its samples, keeps a bounded history of them and serves it; a subscriber delivers each publisher's
samples exactly once and in order, asking the histories for what a cut link lost.

Parts, each with its own state and locks (see their docstrings):
- `session`: the Zenoh session, the only module that imports zenoh
- `wire`: the numbering attachment and history query format, both ends
- `publishing`: numbered publishers and their histories
- `inbox`: the bounded queue a stage takes its samples from
- `delivery`: in-order delivery and gap repair from the histories
- `membership`: stage liveliness, done markers, losses that fail the stage
- `facade`: `Bus`, which composes them
`BusConfig` lives in `octolog.kit.busconfig`, importable without any of this.
"""

from __future__ import annotations

from octolog.kit.bus.facade import Bus, serve_router, wait_interruptibly
from octolog.kit.bus.inbox import Received
from octolog.kit.bus.publishing import Publisher, keeps_all
from octolog.kit.bus.session import zenoh_config
from octolog.kit.busconfig import BusConfig

__all__ = ["Bus", "BusConfig", "Publisher", "Received", "keeps_all", "serve_router", "wait_interruptibly",
           "zenoh_config"]
