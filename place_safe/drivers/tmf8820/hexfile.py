"""The RAM patch: a user-supplied Intel HEX file of one contiguous segment, parsed with ``intelhex``.

ams distributes the TMF8820 application patch as an Intel HEX file; place_safe never ships it. The
driver downloads ``RamPatch.data`` to ``RamPatch.address`` through the bootloader (128 bytes per
command) and starts it. :func:`write_patch` writes a HEX file (for synthetic test patches).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from place_safe.exceptions import ConfigError


@dataclass(frozen=True)
class RamPatch:
    """``data`` to be written to RAM starting at ``address`` (16-bit bootloader address space)."""

    address: int
    data: bytes

    def chunks(self, size: int) -> list[tuple[int, bytes]]:
        """(address, bytes) pieces of at most ``size`` bytes, in order."""
        return [(self.address + i, self.data[i:i + size]) for i in range(0, len(self.data), size)]


#: The Intel HEX end-of-file record: a patch file ends with it (and holds nothing after it).
EOF_RECORD = ":00000001FF"


def load_patch(path: str | Path) -> RamPatch:
    """Parse an Intel HEX RAM patch; :class:`ConfigError` (one line) if it is missing or unusable."""
    from intelhex import IntelHex, IntelHexError

    from place_safe.io.input_file import input_file_problem

    p = Path(path)
    if (why := input_file_problem(p)) is not None:  # also no FIFO or device, and a bounded size
        raise ConfigError(f"RAM patch {p} {why} (the TMF8820 patch is an Intel HEX file from ams)")
    try:
        ih = IntelHex(str(p))
    except (IntelHexError, ValueError, UnicodeDecodeError) as exc:
        raise ConfigError(f"RAM patch {p} is not a valid Intel HEX file: {str(exc).splitlines()[0]}") from None
    records = [line.strip() for line in p.read_text(encoding="ascii", errors="replace").splitlines() if line.strip()]
    ends = [i for i, line in enumerate(records) if line.upper() == EOF_RECORD]
    if not ends and records:  # (IntelHex reads a file cut off between records as a shorter, valid patch)
        raise ConfigError(f"RAM patch {p} has no end-of-file record ({EOF_RECORD}): the file is cut off")
    if ends and ends[0] != len(records) - 1:
        raise ConfigError(f"RAM patch {p} has {len(records) - 1 - ends[0]} record(s) after its end-of-file record")
    segments = ih.segments()
    if not segments:
        raise ConfigError(f"RAM patch {p} holds no data")
    if len(segments) != 1:
        raise ConfigError(f"RAM patch {p} has {len(segments)} segments; expected one contiguous segment")
    start, stop = segments[0]
    if stop > 0x10000:
        raise ConfigError(f"RAM patch {p} ends at 0x{stop:x}, beyond the bootloader's 16-bit addresses")
    return RamPatch(start, ih.tobinstr(start=start, end=stop - 1))


def write_patch(path: str | Path, patch: RamPatch) -> Path:
    """Write ``patch`` as an Intel HEX file (16 data bytes per record)."""
    from intelhex import IntelHex

    ih = IntelHex()
    ih.puts(patch.address, patch.data)
    ih.write_hex_file(str(path))
    return Path(path)


__all__ = ["RamPatch", "load_patch", "write_patch"]
