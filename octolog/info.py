"""`octolog info`: what an MCAP file holds, readable by a person."""

from __future__ import annotations

from pathlib import Path

from octolog.mcaplog import summarize


def describe(path: Path) -> str:
    s = summarize(path)
    lines = [f"{path}: {s.size_bytes / 1e6:.1f} MB, profile {s.profile or '(none)'}, "
             + ("complete" if s.complete else f"INCOMPLETE: {s.problem}")]
    if s.topics:
        t0 = min(t.first_ns for t in s.topics.values())
        t1 = max(t.last_ns for t in s.topics.values())
        lines.append(f"  span {(t1 - t0) * 1e-9:.2f} s, {sum(t.count for t in s.topics.values())} messages")
    width = max((len(n) for n in s.topics), default=0)
    for name in sorted(s.topics):
        t = s.topics[name]
        span = (t.last_ns - t.first_ns) * 1e-9
        rate = (t.count - 1) / span if span > 0 else 0.0
        lines.append(f"  /{name:<{width}}  {t.count:6d} msgs  {rate:6.1f} Hz  {t.msgtype}")
    for name in sorted(s.metadata):
        keys = ", ".join(sorted(s.metadata[name]))
        lines.append(f"  metadata {name}: {keys}")
    if not s.complete:
        lines.append(f"  {sum(t.count for t in s.topics.values())} messages are readable before the damage")
    return "\n".join(lines)
