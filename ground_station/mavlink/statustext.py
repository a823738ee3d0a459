"""Whole STATUSTEXT messages from MAVLink 2 chunks: the one reassembler of the ground station.

A STATUSTEXT carries at most 50 characters. MAVLink 2 sends a longer text as chunks sharing a
non-zero `id`, numbered by `chunk_seq` from 0; the last chunk is the first one shorter than 50
characters (a text whose length is a multiple of 50 ends with an empty chunk, which some senders
omit). `id == 0` is a text in one frame.

`StatusTextAssembler` is a pure state machine (no clock of its own, no I/O): `add(msg, now)` returns
the whole texts the message completes, `flush(now)` returns texts whose chunks stopped arriving
(`STALE_S` after the last one: an omitted terminator or a lost chunk still yields the text, with
`[...]` where a chunk is missing). `Link` and the monitor's `VehicleView` both use it, so a reason
reads the same everywhere and as MAVProxy shows it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

CHUNK_CHARS = 50
STALE_S = 0.5  # a chunked text with no new chunk for this long is complete as far as it goes
MISSING = "[...]"


@dataclass
class StatusText:
    """One whole text: who sent it, its severity and when its last chunk arrived."""

    text: str
    severity: int
    sysid: int
    compid: int
    t: float


@dataclass
class _Partial:
    severity: int
    t: float
    chunks: dict[int, str] = field(default_factory=dict)

    def text(self) -> str:
        if not self.chunks:
            return ""
        last = max(self.chunks)
        return "".join(self.chunks.get(i, MISSING) for i in range(last + 1))


def _field_text(msg) -> str:
    text = msg.text
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    return text.split("\0", 1)[0]


class StatusTextAssembler:
    """Reassembles chunked STATUSTEXTs per (sysid, compid, id)."""

    def __init__(self, stale_s: float = STALE_S) -> None:
        self.stale_s = stale_s
        self._partial: dict[tuple[int, int, int], _Partial] = {}

    def add(self, msg, now: float) -> list[StatusText]:
        """Fold one STATUSTEXT in; returns the texts it completes (0, 1, or
        more when it also pushes out a stale one)."""
        out = self.flush(now)
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        text = _field_text(msg)
        text_id = getattr(msg, "id", 0) or 0  # MAVLink 1 frames have no id: one frame, one text
        if text_id == 0:
            out.append(StatusText(text, msg.severity, sysid, compid, now))
            return out
        key = (sysid, compid, text_id)
        seq = getattr(msg, "chunk_seq", 0) or 0
        part = self._partial.get(key)
        if part is not None and seq in part.chunks:  # the id was reused: the old text is over
            out.append(self._finish(key, part))
            part = None
        if part is None:
            part = self._partial[key] = _Partial(msg.severity, now)
        part.chunks[seq] = text
        part.t = now
        if len(text.encode("utf-8", errors="replace")) < CHUNK_CHARS:
            out.append(self._finish(key, part))
        return out

    def flush(self, now: float | None = None) -> list[StatusText]:
        """Texts whose chunks stopped arriving `stale_s` ago (all pending ones if `now` is None)."""
        out = []
        for key, part in list(self._partial.items()):
            if now is None or now - part.t >= self.stale_s:
                out.append(self._finish(key, part))
        return out

    def pending(self) -> list[str]:
        """Texts begun but not finished yet (as far as they go)."""
        return [p.text() for p in self._partial.values()]

    def _finish(self, key: tuple[int, int, int], part: _Partial) -> StatusText:
        del self._partial[key]
        return StatusText(part.text(), part.severity, key[0], key[1], part.t)


def holds_for_good(text: str) -> bool:
    """The robot's text when it holds mid-mission until the operator acts: a stall ("item N: stalled:
    ..."), the bumper, or the GCS failsafe's Hold or disarm (a GCS heard again clears it, not the Hold)."""
    return "stalled: " in text or "bumper pressed" in text or (
        text.startswith("GCS failsafe: ") and text.endswith((", Hold", ", disarm")))
