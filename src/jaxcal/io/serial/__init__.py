"""Serial UWB devices: wire-format decoders (pure functions on bytes) and their incremental stream decoders.

* `nlink`: Nooploop LinkTrack NLink binary frames.
* `dwm1001`: Qorvo/Decawave DWM1001 PANS UART, TLV (generic) mode and shell (`lec`, `les`, `lep`) mode.
* `encode`: encoders for the same formats (test streams, simulators, the fuzz benchmark).

`make_decoder(protocol)` returns a decoder with `feed(bytes) -> list[Frame]`, `finish()` and `stats`.
"""

from __future__ import annotations

from jaxcal.io.serial.frames import DecoderStats, Frame, Range

PROTOCOLS = ("nlink", "dwm1001-tlv", "dwm1001-shell")

__all__ = ["Frame", "Range", "DecoderStats", "PROTOCOLS", "make_decoder"]


def make_decoder(protocol: str, self_id: str | None = None):
    """A fresh incremental decoder for `protocol` (one of `PROTOCOLS`).

    Args:
        protocol: ``"nlink"``, ``"dwm1001-tlv"`` or ``"dwm1001-shell"``.
        self_id: DWM1001 only: id given to the module on the serial port (its ranges' own end), since
            the DWM1001 outputs do not name it. Default ``"tag"`` (``"anchor"`` for anchor-node TLV).
    """
    from jaxcal.errors import JaxcalError

    if protocol == "nlink":
        from jaxcal.io.serial.nlink import NLinkDecoder

        return NLinkDecoder()
    if protocol == "dwm1001-tlv":
        from jaxcal.io.serial.dwm1001 import TLVDecoder

        return TLVDecoder(self_id=self_id)
    if protocol == "dwm1001-shell":
        from jaxcal.io.serial.dwm1001 import ShellDecoder

        return ShellDecoder(self_id=self_id)
    raise JaxcalError(f"unknown protocol {protocol!r} (known: {', '.join(PROTOCOLS)})")
