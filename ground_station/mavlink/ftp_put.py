"""The put of a policy upload as a pure state machine, standard MAVLink FTP opcodes only.

Rounds of CreateFile / OpenFileWO, 239-byte WriteFiles in a window, TerminateSession and
CalcFileCRC32, whose answer (MAVLink FTP's CRC32 is linear over GF(2)) tells which unanswered writes
were lost, so a lost ACK costs no copy of its block. No socket, no clock: `poll(now)` returns the
request payloads to send, `on_reply(payload, now)` takes every FTP reply
(`ground_station.mavlink.ftp_upload` is the shell on a `Link`). The method, why not pymavlink's
`MAVFTP.cmd_put`, and the figures: docs/mavlink.md, "The put". CreateFile and TerminateSession are
re-sent with the same seq and bytes, so the robot's retry cache answers a copy instead of running it
twice.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from firmware_py.mavlink.ftp_server import HEADER, MAX_DATA, Nak, Op
from firmware_py.storage import ftp_crc32

# the opcodes this engine sends and reads; the FTP contract (header, sizes, codes) is the server's
OP_TERMINATE, OP_RESET, OP_CREATE, OP_WRITE = Op.TERMINATE_SESSION, Op.RESET_SESSIONS, Op.CREATE_FILE, Op.WRITE_FILE
OP_OPEN_WO, OP_CRC, OP_ACK, OP_NAK = Op.OPEN_FILE_WO, Op.CALC_FILE_CRC32, Op.ACK, Op.NAK
NAK_INVALID_SESSION = Nak.INVALID_SESSION
MAX_COPIES = 10  # of one control request before the put gives up (the caller may put again)
OP_NAMES: dict[int, str] = {OP_TERMINATE: "TerminateSession", OP_CREATE: "CreateFile", OP_OPEN_WO: "OpenFileWO",
            OP_CRC: "CalcFileCRC32"}
UNKNOWNS_PER_ROUND = 20  # expected unanswered writes per round (CRC32: 32 equations)
MAX_UNKNOWNS = 28  # more unknowns than this: a wrong solution gets too likely (2^(n-32))
CUT_UNKNOWNS = 24  # a round ends early with this many writes unanswered (window still out)
FIRST_ROUND_BLOCKS = 56
TWICE_AT_MOST = 3  # a last round of this many blocks or fewer sends each twice


def request(seq: int, session: int, opcode: int, offset: int = 0, data: bytes = b"") -> bytes:
    """One FTP request payload (header + data, unpadded)."""
    return HEADER.pack(seq & 0xFFFF, session, opcode, len(data), 0, 0, 0, offset) + data


def solve_gf2(vectors: list[int], target: int) -> list[int] | None:
    """Indices i with XOR of vectors[i] == target, if exactly one such set
    exists (the vectors are linearly independent over GF(2)); else None."""
    basis: list[tuple[int, int]] = []  # (vector, mask of the indices it is the XOR of), by leading bit
    for i, v in enumerate(vectors):
        mask = 1 << i
        for b, m in basis:
            if v ^ b < v:
                v, mask = v ^ b, mask ^ m
        if v == 0:
            return None  # dependent: two sets of blocks would give the same CRC
        basis.append((v, mask))
        basis.sort(reverse=True)
    mask = 0
    for b, m in basis:
        if target ^ b < target:
            target, mask = target ^ b, mask ^ m
    if target:
        return None
    return [i for i in range(len(vectors)) if mask >> i & 1]


@dataclass
class PutStats:
    writes_sent: int = 0  # WriteFile frames, copies included
    rounds: int = 0  # sessions (CreateFile / OpenFileWO ... TerminateSession + CRC)
    unknown: int = 0  # writes sent whose ACK never came
    solved_lost: int = 0  # of those, found lost by the CRC (the rest: only the ACK was lost)
    unsolved: int = 0  # unknowns the CRC could not resolve (sent again)
    cut: int = 0  # rounds ended early (CUT_UNKNOWNS)
    reopened: int = 0  # sessions opened again: the open sent ahead may have preceded the commit
    blocks: int = 0
    rtt_min: float | None = None
    srtt: float | None = None


@dataclass
class _Tx:
    block: int
    sent_at: float
    order: int


@dataclass
class _Ctrl:
    seq: int
    payload: bytes
    kind: int
    sent_at: float
    copies: int = 1
    order: int = -1  # send order of its last copy (writes and controls share the count)
    behind_writes: bool = False  # sent right after the round's writes: their round trip
    timed: bool = True  # its reply is a round-trip sample (not queued behind writes, not an open)


@dataclass
class FtpPut:
    """See the module docstring. `state`: open -> write -> terminate -> check
    -> (open ... or) done, or failed (`error`, `nak` = the robot's NAK data)."""

    data: bytes
    path: str
    session: int
    seq: int  # the next seq to use; read it back when done (the link's counter)
    block: int = MAX_DATA
    window: int = 6
    min_rto: float = 0.05
    max_rto: float = 2.0
    max_rounds: int = 40
    ctrl_rtt: float | None = None  # a small request's round trip measured before (seeds the timers)
    state: str = "open"
    error: str = ""
    nak: bytes = b""
    stats: PutStats = field(default_factory=PutStats)

    def __post_init__(self) -> None:
        if not 1 <= self.block <= MAX_DATA:
            raise ValueError(f"block must be 1..{MAX_DATA} bytes, got {self.block}")
        self.n_blocks = max(1, -(-len(self.data) // self.block))
        self.stats.blocks = self.n_blocks
        self.crc = ftp_crc32(self.data)
        self.acked: set[int] = set()  # known on the robot
        self.unknown: set[int] = set()  # written, no ACK: on the robot or not
        self.lost: list[int] = []  # known missing: to send, oldest first
        self.next_new = 0
        self.queue: list[int] = []  # this round's blocks still to send
        self.sent: dict[int, _Tx] = {}  # seq -> this round's unanswered writes
        self.flight: set[int] = set()  # the writes counted in the window (not known lost)
        self.order = 0
        self.rack_order = -1  # order of the latest-sent write answered
        self.rack_sent = -1.0
        self.srtt: float | None = None
        self.rttvar = 0.0
        self.rtt_min: float | None = None
        self.ctrl_srtt: float | None = self.ctrl_rtt
        self.ctrls: list[_Ctrl] = []  # control requests awaiting their reply
        self.remote_crc: int | None = None
        self.opened = False  # the file exists on the robot (first session committed)
        self.checking: tuple[set[int], list[int]] | None = None  # (answered, unanswered) at the commit
        self.sid = self.session  # the round's session number
        self.opens = 0  # sessions opened (the session number alternates)
        self.next_open: _Ctrl | None = None  # the next round's OpenFileWO, sent behind the commit
        self.open_ready = False  # that OpenFileWO answered after the commit: the round may write
        self.open_refused = False  # it was refused before the commit's ACK came: open again
        self.outbox: list[bytes] = []  # sent by the first poll after the put finished

    # --- timing -------------------------------------------------------------------
    def rto(self) -> float:
        """Retransmit timeout of a write: SRTT + 4 RTTVAR, at least 2 x SRTT."""
        if self.srtt is None:
            return 0.5
        return min(self.max_rto, max(self.min_rto, self.srtt + 4 * self.rttvar, 2 * self.srtt))

    def ctrl_rto(self, ctrl: _Ctrl) -> float:
        if ctrl.behind_writes:  # queued behind the round's last writes
            return self.rto()
        return 0.3 if self.ctrl_srtt is None else min(self.max_rto, max(self.min_rto, 3 * self.ctrl_srtt))

    def _sample(self, rtt: float) -> None:
        self.rtt_min = rtt if self.rtt_min is None else min(self.rtt_min, rtt)
        if self.srtt is None:
            self.srtt, self.rttvar = rtt, rtt / 2
        else:
            self.rttvar = 0.75 * self.rttvar + 0.25 * abs(self.srtt - rtt)
            self.srtt = 0.875 * self.srtt + 0.125 * rtt
        self.stats.rtt_min, self.stats.srtt = self.rtt_min, self.srtt

    def wake_at(self) -> float | None:
        """When `poll` has something to do without a reply arriving."""
        if self.finished:
            return None
        times = [c.sent_at + self.ctrl_rto(c) for c in self.ctrls]
        times += [self.sent[s].sent_at + self.rto() for s in self.flight]
        return min(times) if times else None

    @property
    def finished(self) -> bool:
        return self.state in ("done", "failed")

    # --- sending ------------------------------------------------------------------
    def _next_seq(self) -> int:
        seq = self.seq
        self.seq = (self.seq + 1) & 0xFFFF
        return seq

    def _control(self, opcode: int, data: bytes, now: float, session: int | None = None,
                 behind_writes: bool = False) -> _Ctrl:
        """A control request, due at the next `poll` (which sends it)."""
        seq = self._next_seq()
        payload = request(seq, self.sid if session is None else session, opcode, 0, data)
        ctrl = _Ctrl(seq, payload, opcode, float("-inf"), copies=0, behind_writes=behind_writes,
                     timed=not behind_writes and opcode != OP_OPEN_WO)
        self.ctrls.append(ctrl)
        return ctrl

    def _write(self, block: int, now: float) -> bytes:
        seq = self._next_seq()
        off = block * self.block
        self.sent[seq] = _Tx(block, now, self.order)
        self.flight.add(seq)
        self.order += 1
        self.stats.writes_sent += 1
        return request(seq, self.sid, OP_WRITE, off, self.data[off:off + self.block])

    def _round_size(self) -> int:
        """Blocks to write this round: about UNKNOWNS_PER_ROUND unanswered ones expected."""
        if self.stats.writes_sent == 0:
            return FIRST_ROUND_BLOCKS
        frac = self.stats.unknown / self.stats.writes_sent
        return max(8, int(UNKNOWNS_PER_ROUND / frac)) if frac > 0 else self.n_blocks

    def _open(self, now: float) -> None:
        """CreateFile (first round) or OpenFileWO, on a session number other
        than the last round's: a late copy of that round's TerminateSession
        then finds no session instead of ending this one."""
        self.opens += 1
        self.sid = (self.session + self.opens % 2) & 0xFF
        self.state = "open"
        self._control(OP_OPEN_WO if self.opened else OP_CREATE, self.path.encode() + b"\0", now)

    def _open_next(self, now: float, behind_writes: bool) -> None:
        """The next round's OpenFileWO, sent right behind this round's TerminateSession and
        CalcFileCRC32 (pipelined: the link is FIFO and the robot serves requests in order, so it
        opens the committed file). Its writes wait for the commit's ACK: only an ACK of the
        commit's first copies proves the commit ran before this open (`_reopen`)."""
        self.opens += 1
        self.sid = (self.session + self.opens % 2) & 0xFF
        self.open_ready = self.open_refused = False
        self.next_open = self._control(OP_OPEN_WO, self.path.encode() + b"\0", now, behind_writes=behind_writes)

    def _reopen(self, now: float) -> None:
        """The pipelined open may have run before the commit (or was refused for it): open the same
        session again (the robot replaces it; no write went to it yet)."""
        self.ctrls = [c for c in self.ctrls if c is not self.next_open]
        self.stats.reopened += 1
        self.open_ready = self.open_refused = False
        self.next_open = self._control(OP_OPEN_WO, self.path.encode() + b"\0", now)

    def poll(self, now: float) -> list[bytes]:
        """Requests due now (first call: the CreateFile)."""
        if self.finished:
            out, self.outbox = self.outbox, []
            return out
        out = []
        if self.state == "open" and not self.ctrls:
            self._open(now)
        for c in self.ctrls:  # first send, or a copy: same seq and bytes (the retry cache answers)
            if now - c.sent_at >= self.ctrl_rto(c) and c.copies >= MAX_COPIES:
                self._fail(OP_NAMES.get(c.kind, str(c.kind)), b"", f"no reply to {OP_NAMES.get(c.kind)} "
                                                                    f"({c.copies} copies)")
                return []
            if now - c.sent_at >= self.ctrl_rto(c):
                c.sent_at, c.order = now, self.order
                self.order += 1
                c.copies += 1
                out.append(c.payload)
                if c.kind == OP_TERMINATE or c.kind == OP_CRC and self.next_new >= self.n_blocks:
                    # harmless twice (retry cache): two chances. The CRC only when the put waits
                    # for it; mid-put its answer only reorders the next round's queue
                    out.append(c.payload)
        if self.state != "write":
            return out
        rto = self.rto()
        for seq in sorted(self.flight):  # the round's tail: no later ACK will tell
            if now - self.sent[seq].sent_at >= rto:
                self.flight.discard(seq)  # still in `sent`: a late ACK counts
        if len(self.sent) - len(self.flight) >= CUT_UNKNOWNS and self.queue:
            # an unlucky round: more unanswered writes already than the CRC can sort out
            # with the window's still to come; the rest waits for the next round
            self.lost[:0] = list(dict.fromkeys(b for b in self.queue if b not in self.acked))
            self.queue.clear()
            self.stats.cut += 1
        while len(self.flight) < self.window and self.queue:
            block = self.queue.pop(0)
            if block not in self.acked:  # a second copy of an answered block is not needed
                out.append(self._write(block, now))
        if not self.queue:  # every write of the round is out: commit behind them (FIFO link),
            self.state = "terminate"  # and ask the CRC right behind the commit
            self._control(OP_TERMINATE, b"", now, behind_writes=True)
            self._crc_request(now, behind_writes=True)
            self._open_next(now, behind_writes=True)
            out += self.poll(now)
        return out

    def _crc_request(self, now: float, behind_writes: bool = False) -> None:
        # its own session number: the round's session keeps the Terminate in the retry cache
        self.ctrls = [c for c in self.ctrls if c.kind != OP_CRC]  # an older copy's answer may predate the commit
        self._control(OP_CRC, self.path.encode() + b"\0", now, (self.session + 2) & 0xFF, behind_writes)

    # --- replies ------------------------------------------------------------------
    def on_reply(self, payload: bytes, now: float) -> None:
        """Any FTP reply from the robot; those not ours are ignored."""
        if len(payload) < HEADER.size or self.finished:
            return
        seq, _session, opcode, size, req_opcode, _b, _p, _off = HEADER.unpack_from(payload, 0)
        if opcode not in (OP_ACK, OP_NAK):
            return
        asked = (seq - 1) & 0xFFFF
        data = bytes(payload[HEADER.size:HEADER.size + size])
        ctrl = next((c for c in self.ctrls if c.seq == asked and c.kind == req_opcode), None)
        answered = ctrl.order if ctrl is not None else self.sent[asked].order if asked in self.sent else -1
        for c in self.ctrls:  # a request sent before an answered one, unanswered: lost, send again
            if c is not ctrl and 0 <= c.order < answered:
                c.sent_at = float("-inf")
        if ctrl is not None:
            self.ctrls.remove(ctrl)
            if ctrl.timed and ctrl.copies == 1:  # Karn: a copy's reply may answer the first
                # (an OpenFileWO's reply waits for the robot to copy the file: no sample)
                rtt = now - ctrl.sent_at
                self.ctrl_srtt = rtt if self.ctrl_srtt is None else 0.875 * self.ctrl_srtt + 0.125 * rtt
            self._control_reply(ctrl, opcode, data, now)
        elif req_opcode == OP_WRITE and asked in self.sent:
            if opcode == OP_NAK:
                self._fail("WriteFile", data)
                return
            tx = self.sent.pop(asked)
            self.flight.discard(asked)
            self._sample(now - tx.sent_at)  # one seq per copy: the sample is exact
            self.acked.add(tx.block)
            if tx.order > self.rack_order:
                self.rack_order, self.rack_sent = tx.order, tx.sent_at
            margin = (self.rtt_min or 0.0) / 4
            for s in sorted(self.flight):  # sent before an answered write: no ACK is coming
                t = self.sent[s]
                if t.order < self.rack_order and t.sent_at + margin < self.rack_sent:
                    self.flight.discard(s)  # frees its slot; the CRC will tell what happened

    def _control_reply(self, ctrl: _Ctrl, opcode: int, data: bytes, now: float) -> None:
        kind = ctrl.kind
        if kind in (OP_CREATE, OP_OPEN_WO):
            if ctrl is self.next_open and self.state == "terminate":
                # answered before the commit's ACK: the commit may not have run before it
                # (refused: the file may not exist yet); decided when the commit answers
                self.open_ready = opcode == OP_ACK
                self.open_refused = opcode != OP_ACK
                return
            if opcode != OP_ACK:
                self._fail("CreateFile" if kind == OP_CREATE else "OpenFileWO", data)
                return
            if ctrl is self.next_open:
                self.open_ready = True
                if self.state != "open":
                    return  # "check": the CRC decides what the round writes
            self.next_open = None
            self._start_round()
        elif kind == OP_TERMINATE:
            # NAK InvalidSession on a copy: the first copy closed the session after the
            # robot's retry cache expired; the CRC tells what the robot holds
            if opcode != OP_ACK and data[:1] != bytes([NAK_INVALID_SESSION]):
                self._fail("TerminateSession", data)
                return
            self.opened = True
            for tx in self.sent.values():
                if tx.block not in self.acked:
                    self.unknown.add(tx.block)
                    self.stats.unknown += 1
            self.sent.clear()
            self.flight.clear()
            self.unknown -= self.acked
            stale = self.checking is not None  # the last round's CRC never came: one check for both
            if self.checking is not None:
                self.unknown.update(self.checking[1])
            self.checking = (set(self.acked), sorted(self.unknown))
            self.unknown.clear()
            for c in self.ctrls:  # the writes have drained (FIFO): the answers are one round trip off
                if c.kind in (OP_CRC, OP_OPEN_WO) and c.behind_writes:
                    c.behind_writes, c.sent_at = False, now
            if stale or ctrl.copies > 1 or not any(c.kind == OP_CRC for c in self.ctrls):
                # the CRC asked behind the first Terminate may have run before the commit
                # (that copy lost, a later one ran it): ask again, behind this ACK
                self._crc_request(now)
            if (ctrl.copies > 1 or self.open_refused) and self.next_open is not None:
                self._reopen(now)  # a copy ran the commit, perhaps after the pipelined open
            if self.next_new < self.n_blocks or self.lost:  # more to write whatever the CRC says
                self.state = "open"
                if self.open_ready:
                    self.next_open = None
                    self._start_round()
            else:
                self.state = "check"
        elif kind == OP_CRC:
            if self.checking is None:
                return  # answered before the commit was confirmed: asked again then
            if opcode != OP_ACK or len(data) != 4:
                self._fail("CalcFileCRC32", data)
                return
            self._check(struct.unpack("<I", data)[0], now)

    def _start_round(self) -> None:
        self.stats.rounds += 1
        size = self._round_size()
        self.queue = list(self.lost)
        self.lost.clear()
        while len(self.queue) < size and self.next_new < self.n_blocks:
            self.queue.append(self.next_new)
            self.next_new += 1
        if self.next_new >= self.n_blocks and len(self.queue) <= TWICE_AT_MOST:
            # the last few blocks: a second copy (one frame of air each) is cheaper than
            # another round (two round trips, the CRC and a session)
            self.queue = self.queue * 2
        self.state = "write"

    def _check(self, remote: int, now: float) -> None:
        """Which unanswered writes reached the robot, from its CRC32 of the
        committed file (`_solve`); the missing ones are written next."""
        assert self.checking is not None
        acked, unknown = self.checking
        self.checking = None
        self.remote_crc = remote
        present = self._solve(remote, acked, unknown)
        if present is None:  # cannot tell: every unanswered block is sent again
            if not unknown:
                self._fail("CalcFileCRC32", b"", f"robot CRC32 0x{remote:08x} is not the file's "
                                                 f"with every block acknowledged")
                return
            self.stats.unsolved += len(unknown)
            present = []
        else:
            self.stats.solved_lost += len(unknown) - len(present)
        self.acked.update(present)
        missing = [b for b in unknown if b not in self.acked]
        if self.state == "write":  # the next round is under way: these go first
            self.queue[:0] = missing
        else:
            self.lost.extend(missing)
        if self.state != "check":
            return
        if not self.lost and self.next_new >= self.n_blocks and remote == self.crc:
            self.state = "done"
            if self.next_open is not None:  # the pipelined session is not needed: close it uncommitted
                self.outbox.append(request(self._next_seq(), self.sid, OP_RESET))
        elif self.stats.rounds >= self.max_rounds:
            self._fail("put", b"", f"{len(self.lost)} blocks still missing after {self.stats.rounds} rounds")
        elif self.next_open is None:
            self._open(now)
        else:
            self.state = "open"
            if self.open_ready:
                self.next_open = None
                self._start_round()

    def _solve(self, remote: int, acked: set[int], unknown: list[int]) -> list[int] | None:
        """The unanswered blocks that are on the robot, if its CRC32 tells them apart; else None.

        CRC32 as MAVLink FTP computes it (initial 0, no final xor) is linear over GF(2): for a file
        of fixed length, CRC(a xor b) = CRC(a) xor CRC(b). The robot's file is the blocks it
        received, holes reading as zeros, as long as the highest one it received. For each
        hypothesis on that highest block (an unanswered block from the top down, until an answered
        one), CRC(robot) xor CRC(answered blocks only) is the XOR of CRC(block alone in a zero file)
        over the unanswered blocks that arrived: 32 equations over GF(2), solved when the candidates
        are independent (UNKNOWNS_PER_ROUND keeps them well under 32), then checked by computing the
        whole file's CRC once more."""
        pending = set(unknown)
        answers: list[list[int]] = []
        for top in sorted(acked | pending, reverse=True):
            length = min(len(self.data), (top + 1) * self.block)
            below = [u for u in unknown if u < top]
            if len(below) > MAX_UNKNOWNS:
                return None
            known = [b for b in acked if b <= top] + ([top] if top in pending else [])
            base = self._content(length, known)
            found = solve_gf2([ftp_crc32(self._content(length, [u])) for u in below], remote ^ ftp_crc32(base))
            if found is not None:
                answers.append([below[i] for i in found] + ([top] if top in pending else []))
            if top not in pending:
                break  # an answered block: the file reaches at least this far
        return answers[0] if len(answers) == 1 else None  # two lengths fit: cannot tell

    def _content(self, length: int, blocks: list[int]) -> bytearray:
        buf = bytearray(length)
        for b in blocks:
            off = b * self.block
            buf[off:off + self.block] = self.data[off:min(off + self.block, length)]
        return buf

    def _fail(self, what: str, data: bytes, text: str = "") -> None:
        self.state, self.nak = "failed", data
        self.error = text or f"{what} NAK {data[0] if data else '?'}"
