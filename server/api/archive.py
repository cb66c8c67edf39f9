"""A directory (a recording) as one uncompressed tar stream whose length is known before it is
sent: its chunks are binary rows that hardly compress, and a download with a Content-Length
can show its progress."""

from __future__ import annotations

import tarfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

TAR_MEDIA_TYPE = "application/x-tar"
_TAR_BLOCK_BYTES = tarfile.BLOCKSIZE
_TAR_RECORD_BYTES = tarfile.RECORDSIZE
_READ_BYTES = 1 << 20


@dataclass(frozen=True)
class Archive:
    """A recording as an uncompressed tar stream (``NAME.burrrec/...`` members): its chunks
    are binary rows that hardly compress, and a tar's length is known before it is sent."""

    filename: str
    size_bytes: int
    _members: tuple[tuple[bytes, Path, int], ...]

    def chunks(self) -> Iterator[bytes]:
        """The archive's bytes, one file read at a time (``_READ_BYTES`` each)."""
        sent = 0
        for header, path, size in self._members:
            yield header
            left = size
            with open(path, "rb") as f:
                while left > 0:
                    data = f.read(min(_READ_BYTES, left))
                    if not data:  # shrank since it was listed: keep the header's promise
                        data = b"\0" * left
                    left -= len(data)
                    yield data
            yield b"\0" * (-size % _TAR_BLOCK_BYTES)
            sent += len(header) + size + (-size % _TAR_BLOCK_BYTES)
        yield b"\0" * (self.size_bytes - sent)


def tar_archive(path: Path) -> Archive:
    """The directory ``path`` as a tar archive of ``NAME/...`` members (regular files only,
    symbolic links left out), its size computed before a byte is read."""
    members = []
    size = 0
    for file in sorted(p for p in path.rglob("*") if p.is_file() and not p.is_symlink()):
        st = file.stat()
        info = tarfile.TarInfo(f"{path.name}/{file.relative_to(path).as_posix()}")
        info.size, info.mtime, info.mode = st.st_size, int(st.st_mtime), 0o644
        header = info.tobuf(tarfile.PAX_FORMAT)
        members.append((header, file, st.st_size))
        size += len(header) + st.st_size + (-st.st_size % _TAR_BLOCK_BYTES)
    size += 2 * _TAR_BLOCK_BYTES  # the end-of-archive marker
    size += -size % _TAR_RECORD_BYTES
    return Archive(path.name + ".tar", size, tuple(members))
