"""A file's voxel bytes, read a slab at a time: stored raw, gzip- or bzip2-compressed.

Compressed data is inflated as it is read, into the caller's slab, never whole, and checked
against the size its header declares while it streams: more than the header declares is
refused the moment the first byte too many comes out, less as soon as the data ends. A gzip
payload is also checked before a byte is inflated: its trailer holds the inflated size
(modulo 4 GiB), so a bomb — a few megabytes of zeros that inflate to gigabytes behind a
header for a small volume — is refused at once, not after gigabytes of inflating.
"""

from __future__ import annotations

import bz2
import os
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Protocol

from .errors import BoneFileError

#: Compressed bytes read from the file at a time.
CHUNK_BYTES = 1 << 20
GZIP_MAGIC = b"\x1f\x8b"
BZIP2_MAGIC = b"BZh"
#: Gzip's FLG.FEXTRA: blocked gzip (BGZF) writes many members, each with its own trailer.
_GZIP_FEXTRA = 0x04
ENCODINGS = ("raw", "gzip", "bzip2")


class ByteReader(Protocol):
    """An open payload: exactly its declared bytes, a slab at a time."""

    def readinto(self, view: memoryview) -> None:
        """Fill ``view`` entirely (BoneFileError when the data ends first)."""

    def finish(self) -> None:
        """After the last slab: BoneFileError when more data follows than was declared."""

    def close(self) -> None: ...


@dataclass(frozen=True)
class Payload:
    """Where a volume's bytes are in a file and how they are stored.

    Attributes:
        owner: the file errors name (a detached NRRD's header, not its data file).
        file: the file holding the bytes.
        offset: where the stored payload starts in ``file``.
        encoding: "raw", "gzip" or "bzip2".
        size: the voxel bytes the header declares.
        skip: bytes before the voxels: decoded bytes for compressed data (a ``.nii.gz``'s
            header, NRRD's byte skip), file bytes for raw data (-1: the voxels end the file).
        lines: NRRD's line skip: lines of ``file`` after ``offset`` before the payload.
    """

    owner: Path
    file: Path
    offset: int
    encoding: str
    size: int
    skip: int = 0
    lines: int = 0

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise ValueError(f"encoding must be one of {ENCODINGS}, got {self.encoding!r}")

    def check(self) -> None:
        """What can be known without inflating: raw data long enough, a gzip trailer that
        agrees with the header.

        Raises:
            BoneFileError: truncated raw data, or gzip data of another size.
        """
        with self._open_file() as f:
            start = f.tell()
            f.seek(0, os.SEEK_END)
            stored = f.tell() - start
            if self.encoding == "raw":
                have = stored if self.skip < 0 else stored - self.skip
                if have < self.size:
                    raise BoneFileError(self.owner, f"the voxel data is truncated: "
                                                    f"{max(have, 0):,} bytes where the header "
                                                    f"declares {self.size:,}")
            elif self.encoding == "gzip":
                f.seek(start)
                self._check_gzip_trailer(f, stored)

    def _check_gzip_trailer(self, f: BinaryIO, stored: int) -> None:
        head = f.read(4)
        if len(head) < 4 or stored < 18:
            raise BoneFileError(self.owner, "the voxel data is truncated: the gzip data "
                                            f"is {stored} bytes")
        if head[:2] != GZIP_MAGIC:
            raise BoneFileError(self.owner, "the voxel data is damaged: it is not gzip "
                                            "data, as the header says")
        if head[3] & _GZIP_FEXTRA:
            return  # blocked gzip (several members): the stream is checked as it inflates
        f.seek(-4, os.SEEK_END)
        trailer = int.from_bytes(f.read(4), "little")
        expected = self.skip + self.size
        if trailer != expected & 0xFFFFFFFF:
            raise BoneFileError(self.owner, f"the gzip data inflates to {trailer:,} bytes "
                                            f"(its trailer, modulo 4 GiB) where the header "
                                            f"declares {expected:,}: refused before inflating "
                                            "it")

    def _open_file(self) -> BinaryIO:
        try:
            f = open(self.file, "rb")
        except OSError as exc:
            raise BoneFileError(self.owner, f"cannot read the voxel data in {self.file}: "
                                            f"{exc.strerror or exc}") from None
        try:
            f.seek(self.offset)
            for _ in range(self.lines):
                f.readline()
        except BaseException:
            f.close()
            raise
        return f

    def open(self) -> ByteReader:
        """The payload's bytes from the first voxel on (closed by the caller)."""
        f = self._open_file()
        try:
            if self.encoding == "raw":
                if self.skip < 0:
                    f.seek(-self.size, os.SEEK_END)
                else:
                    f.seek(self.skip, os.SEEK_CUR)
                return _Raw(self, f)
            reader = _Inflated(self, f)
            reader.discard(self.skip)
            return reader
        except BaseException:
            f.close()
            raise


class _Raw:
    def __init__(self, payload: Payload, f: BinaryIO) -> None:
        self.payload = payload
        self.f = f
        self.done = 0

    def readinto(self, view: memoryview) -> None:
        filled = 0
        while filled < len(view):
            n = self.f.readinto(view[filled:])
            if not n:
                raise BoneFileError(self.payload.owner, "the voxel data is truncated: "
                                                        f"{self.done + filled:,} bytes where "
                                                        f"the header declares "
                                                        f"{self.payload.size:,}")
            filled += n
        self.done += filled

    def finish(self) -> None:
        pass  # trailing bytes after raw voxels are no one's memory: allowed, as before

    def close(self) -> None:
        self.f.close()


class _Inflated:
    """Decoded bytes of a gzip or bzip2 stream, never more at a time than asked for. Several
    concatenated members read as one stream (as gzip and bzip2 tools read them)."""

    def __init__(self, payload: Payload, f: BinaryIO) -> None:
        self.payload = payload
        self.f = f
        self.gzip = payload.encoding == "gzip"
        self.magic = GZIP_MAGIC if self.gzip else BZIP2_MAGIC
        self.done = 0  # decoded bytes handed out (the skip included)
        self._start(b"")

    def _start(self, data: bytes) -> None:
        self.inflater = (zlib.decompressobj(16 + zlib.MAX_WBITS) if self.gzip
                         else bz2.BZ2Decompressor())
        self.input = data

    def _read(self, n: int) -> bytes:
        """Up to ``n`` decoded bytes; b"" at the end of the data."""
        try:
            while True:
                inflater = self.inflater
                if inflater.eof:
                    rest = inflater.unused_data + self.input
                    while len(rest) < len(self.magic):
                        more = self.f.read(CHUNK_BYTES)
                        if not more:
                            break
                        rest += more
                    if not rest.startswith(self.magic):
                        return b""  # the end; bytes after the last member are ignored
                    self._start(rest)
                    continue
                data, self.input = self.input, b""
                if not data and (self.gzip or inflater.needs_input):
                    data = self.f.read(CHUNK_BYTES)
                    if not data:
                        # The file ended inside a member: what the inflater still holds,
                        # then the end.
                        return inflater.decompress(b"", n) if self.gzip else b""
                out = inflater.decompress(data, n)
                if self.gzip:
                    self.input = inflater.unconsumed_tail
                if out:
                    return out
        except (zlib.error, OSError, EOFError, ValueError) as exc:
            raise BoneFileError(self.payload.owner, f"the voxel data is damaged or "
                                                    f"truncated: {exc}") from None

    def discard(self, n: int) -> None:
        while n > 0:
            out = self._read(min(n, CHUNK_BYTES))
            if not out:
                raise self._truncated()
            n -= len(out)
            self.done += len(out)

    def readinto(self, view: memoryview) -> None:
        filled = 0
        while filled < len(view):
            out = self._read(min(len(view) - filled, CHUNK_BYTES))
            if not out:
                self.done += filled
                raise self._truncated()
            view[filled:filled + len(out)] = out
            filled += len(out)
        self.done += filled

    def finish(self) -> None:
        if self._read(1):
            declared = self.payload.skip + self.payload.size
            raise BoneFileError(self.payload.owner, f"the compressed data inflates past the "
                                                    f"{declared:,} bytes its header declares")

    def _truncated(self) -> BoneFileError:
        declared = self.payload.skip + self.payload.size
        return BoneFileError(self.payload.owner, f"the voxel data is truncated: it inflates "
                                                 f"to {self.done:,} bytes where the header "
                                                 f"declares {declared:,}")

    def close(self) -> None:
        self.f.close()
