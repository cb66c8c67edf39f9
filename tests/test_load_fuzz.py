"""Corrupted bone files: whatever the bytes, a load returns a bone or raises BoneFileError."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.bench import bone_files
from burrforce.server.bone.bone import Bone
from burrforce.server.bone.loaders import BoneFileError, LoadOptions, load_bone
from burrforce.server.bone.phantoms import phantom

SPACING = LoadOptions(spacing_mm=(1.0, 1.0, 1.0))
#: Each code path: compressed and raw NIfTI, labels and CT, colour and grey PNG, …
FORMATS = list(bone_files.FORMAT_WRITERS)


@pytest.fixture(scope="module")
def originals(tmp_path_factory) -> dict[str, Path]:
    bone = phantom("workpiece", 4.0)  # a few hundred voxels: small files, fast loads
    root = tmp_path_factory.mktemp("originals")
    return {fmt: bone_files.write(bone, fmt, root) for fmt in FORMATS}


def _target(original: Path) -> Path:
    """The file a mutation hits: the file itself, or the middle file of a folder."""
    if original.is_dir():
        files = sorted(original.iterdir())
        return files[len(files) // 2]
    return original


mutation = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("flip"), st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)),
                                        min_size=1, max_size=8)),
    st.tuples(st.just("insert"),
              st.tuples(st.floats(0.0, 1.0), st.binary(min_size=1, max_size=64))),
    st.tuples(st.just("random"), st.binary(min_size=0, max_size=600)),
)


def _mutate(data: bytes, how) -> bytes:
    kind, arg = how
    if kind == "truncate":
        return data[: int(len(data) * arg)]
    if kind == "flip":
        out = bytearray(data)
        for where, xor in arg:
            if out:
                out[min(int(where * len(out)), len(out) - 1)] ^= xor
        return bytes(out)
    if kind == "insert":
        where, extra = arg
        cut = int(where * len(data))
        return data[:cut] + extra + data[cut:]
    return arg


@pytest.mark.filterwarnings("ignore::UserWarning")  # pydicom warns about each bad value
@pytest.mark.parametrize("fmt", FORMATS)
@settings(max_examples=examples(150), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(how=mutation)
def test_corrupted_files_fail_cleanly(fmt, how, originals, tmp_path):
    original = originals[fmt]
    work = tmp_path / "work"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir()
    copy = work / original.name
    if original.is_dir():
        shutil.copytree(original, copy)
    else:
        shutil.copy(original, copy)
    target = _target(copy)
    target.write_bytes(_mutate(target.read_bytes(), how))
    try:
        bone = load_bone(copy, SPACING)
    except BoneFileError as exc:
        assert str(exc.path) in str(exc)
    else:
        assert isinstance(bone, Bone)
        assert bone.grid.density.dtype == np.uint8 and bone.grid.density.ndim == 3
