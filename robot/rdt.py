"""ATI Net F/T (and Axia) Raw Data Transfer (RDT) over UDP: the wire format, shared by the reader (robot.netft) and
the simulated box (robot.simnetft). docs/reference.md has the facts: UDP port 49152 on the box; a request is 8 bytes
big-endian ``>HHI`` (header 0x1234, command, sample count; 0 = endless); a record 36 bytes ``>IIIiiiiii`` (RDT
sequence, F/T sequence, status, Fx Fy Fz Tx Ty Tz in counts). A datagram may hold several records (buffered mode).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

RDT_PORT = 49152
RDT_HEADER = 0x1234
CMD_STOP = 0
CMD_START_REALTIME = 2
CMD_START_BUFFERED = 3
CMD_SET_BIAS = 0x42
REQUEST = struct.Struct(">HHI")
RECORD = struct.Struct(">IIIiiiiii")
SEQ_MOD = 1 << 32                   # the sequence counters are uint32 and wrap


@dataclass(frozen=True)
class RdtRecord:
    rdt_sequence: int               # counts every record sent (a gap: records lost on the way)
    ft_sequence: int                # counts the box's internal samples
    status: int                     # 0: healthy; anything else is the box reporting a problem
    counts: tuple                   # Fx Fy Fz Tx Ty Tz, raw counts (divide by counts per force / torque)


def pack_request(command: int, sample_count: int = 0) -> bytes:
    return REQUEST.pack(RDT_HEADER, command, sample_count)


def unpack_request(data: bytes) -> tuple[int, int] | None:
    """(command, sample count) of a request, None for anything that is not one."""
    if len(data) != REQUEST.size:
        return None
    header, command, count = REQUEST.unpack(data)
    return (command, count) if header == RDT_HEADER else None


def pack_record(rec: RdtRecord) -> bytes:
    return RECORD.pack(rec.rdt_sequence % SEQ_MOD, rec.ft_sequence % SEQ_MOD, rec.status, *rec.counts)


def unpack_records(data: bytes) -> list[RdtRecord]:
    """The records of one datagram; ValueError if its length is not a whole number of records."""
    if not data or len(data) % RECORD.size:
        raise ValueError(f"an RDT datagram of {len(data)} bytes is not a whole number of {RECORD.size}-byte records")
    out = []
    for off in range(0, len(data), RECORD.size):
        v = RECORD.unpack_from(data, off)
        out.append(RdtRecord(v[0], v[1], v[2], tuple(v[3:])))
    return out


def seq_ahead(new: int, last: int) -> int:
    """How many sequence numbers ``new`` lies after ``last`` (1: the next one); <= 0 for a duplicate or a record
    older than ``last`` (reordered on the way), with uint32 wrap-around."""
    d = (new - last) % SEQ_MOD
    return d if d < SEQ_MOD // 2 else d - SEQ_MOD
