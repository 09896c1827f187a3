"""What BagReader found (BagReport), the messages it yields (RawMessage) and its error type."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple


class BagReadError(RuntimeError):
    """A bag could not be read (raised only with strict=True; otherwise see BagReport)."""


class RawMessage(NamedTuple):
    topic: str
    msgtype: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int


@dataclass
class BagReport:
    """What BagReader found. files: the .mcap files in read order; truncated: file -> reason
    (no footer/summary: writer killed or file cut; every complete chunk is still read);
    errors: file -> reason (foreign, garbage, missing, corrupt chunk); warnings: other findings
    (unknown schema encodings, type conflicts, metadata.yaml problems); counts: topic ->
    messages available; topic_types: topic -> type; schema_encodings: topic -> schema encoding."""
    files: list[str] = field(default_factory=list)
    truncated: dict[str, str] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    topic_types: dict[str, str] = field(default_factory=dict)
    schema_encodings: dict[str, str] = field(default_factory=dict)
    #: refusals of records, chunks, messages and schemas over the limits (trainer/bag/limits.py):
    #: one line each, naming the file, the byte offset and the limit
    refused: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.errors and not self.refused

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def summary(self) -> str:
        lines = [f"{len(self.files)} file(s), {self.message_count} message(s)"]
        lines += [f"  {t} [{self.topic_types.get(t, '?')}]: {n}" for t, n in self.counts.items()]
        lines += [f"  TRUNCATED {p}: {r}" for p, r in self.truncated.items()]
        lines += [f"  ERROR {p}: {r}" for p, r in self.errors.items()]
        lines += [f"  REFUSED {r}" for r in self.refused]
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)
