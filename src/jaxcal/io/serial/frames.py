"""Decoded-frame records shared by the serial protocol decoders.

A decoder turns bytes into `Frame`s. Every frame keeps its validated raw bytes (so a recording can be
re-decoded after a decoder fix), its decoded fields (in SI units: metres, volts, dBm, degrees) and the
node-to-node ranges it carries as `Range` tuples, which is all the recorder needs.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, NamedTuple

__all__ = ["Range", "Frame", "DecoderStats", "NAN"]

NAN = math.nan


class Range(NamedTuple):
    """One range measurement carried by a frame.

    Attributes:
        src: id of the node that measured (or reported) the range, e.g. ``"T1"`` or ``"8287"``.
        dst: id of the other node.
        range_m: measured range [m] (may be negative: UWB ranges at short distance are biased).
        fp_rssi: first-path power [dBm], NaN when the frame does not carry it.
        rx_rssi: total receive power [dBm], NaN when absent.
        src_role, dst_role: ``"tag"``, ``"anchor"``, ``"node"``, ... (``"unknown"`` when not known).
    """

    src: str
    dst: str
    range_m: float
    fp_rssi: float = NAN
    rx_rssi: float = NAN
    src_role: str = "unknown"
    dst_role: str = "unknown"


@dataclass(frozen=True, eq=False)
class Frame:
    """A validated frame.

    Attributes:
        type: frame type name, e.g. ``"NodeFrame3"``, ``"loc_get"``, ``"lec"``, ``"unknown"``.
        raw: the validated bytes exactly as received (a whole NLink frame, a whole TLV response, or
            one shell line without its line ending).
        fields: decoded values, in SI units (m, V, dBm, deg); ids as ints.
        ranges: the range measurements the frame carries.
        device_time_ms: the module's own clock (NLink ``local_time``) when the frame carries it.
    """

    type: str
    raw: bytes
    fields: dict[str, Any] = field(default_factory=dict)
    ranges: tuple[Range, ...] = ()
    device_time_ms: int | None = None

    def __eq__(self, other) -> bool:  # frames are equal when they came from the same bytes
        return isinstance(other, Frame) and self.type == other.type and self.raw == other.raw

    def __hash__(self) -> int:
        return hash((self.type, self.raw))


@dataclass
class DecoderStats:
    """Counters of an incremental decoder.

    Attributes:
        frames: frames emitted (of any type, unknown ones included).
        by_type: frames per type name.
        checksum_failures: complete candidate frames of a known type that failed validation (checksum,
            tail byte, length/count consistency, structural walk; for the checksum-less DWM1001
            formats: a response or line that broke its layout rules).
        bytes_skipped: bytes that were not part of any emitted frame (garbage, false headers,
            rejected frames, truncated tails at end of stream).
        bytes_fed: all bytes given to `feed`.
    """

    frames: int = 0
    by_type: Counter = field(default_factory=Counter)
    checksum_failures: int = 0
    bytes_skipped: int = 0
    bytes_fed: int = 0

    def as_dict(self) -> dict[str, Any]:
        """Plain-dict view (JSON-ready)."""
        return {
            "frames": self.frames,
            "by_type": dict(sorted(self.by_type.items())),
            "checksum_failures": self.checksum_failures,
            "bytes_skipped": self.bytes_skipped,
            "bytes_fed": self.bytes_fed,
        }
