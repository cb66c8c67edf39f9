"""Loading a slab at a time: the same bone whatever the slab size, a memory budget checked
from the header, a float64 source never held whole, compressed data checked against its
header as it inflates, and NIfTI headers named for what is wrong with them."""

from __future__ import annotations

import bz2
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from burrforce.server.bench import bone_files
from burrforce.server.bench.large_volumes import write_ct
from burrforce.server.bone.loaders import (
    BoneFileError,
    BoneTooLarge,
    LoadOptions,
    convert,
    load_bone,
    slabs,
)
from burrforce.server.bone.loaders.budget import STREAM_WORK_BYTES, bone_bytes
from burrforce.server.bone.phantoms import phantom

SPACING = LoadOptions(spacing_mm=(0.5, 0.5, 0.5))


@pytest.fixture(scope="module")
def bone():
    return phantom("temporal", 1.0)


@pytest.mark.parametrize("fmt", list(bone_files.FORMAT_WRITERS))
def test_any_slab_size_makes_the_same_bone(fmt, bone, tmp_path, monkeypatch):
    """Slabs of 4 kB split planes into rows and rows across blocks' edges: the bone is the
    one whole slabs make, voxel for voxel."""
    path = bone_files.write(bone, fmt, tmp_path)
    options = LoadOptions(spacing_mm=(1.0, 1.0, 1.0))
    whole = load_bone(path, options)
    monkeypatch.setattr(slabs, "SLAB_BYTES", 4096)
    monkeypatch.setattr(convert, "SLAB_BYTES", 4096)
    sliced = load_bone(path, options)
    np.testing.assert_array_equal(sliced.grid.density, whole.grid.density)
    np.testing.assert_array_equal(sliced.grid.labels, whole.grid.labels)
    assert sliced.volumes_mm3() == whole.volumes_mm3()
    assert sliced.notes == whole.notes
    assert sum(whole.volumes_mm3().values()) == pytest.approx(
        sum(bone.volumes_mm3().values()), rel=0.05)


def test_a_colour_stack_too_large_to_hold_is_decoded_again_for_each_pass(bone, tmp_path):
    path = bone_files.write(bone, "png", tmp_path)
    held = load_bone(path, LoadOptions(spacing_mm=(1.0, 1.0, 1.0)))
    # Room for the bone and a slab, not for the stack's two decoded bytes a voxel.
    tight = bone_bytes(held.grid.shape) + STREAM_WORK_BYTES + 1
    again = load_bone(path, LoadOptions(spacing_mm=(1.0, 1.0, 1.0), memory_budget_bytes=tight))
    np.testing.assert_array_equal(again.grid.density, held.grid.density)
    np.testing.assert_array_equal(again.grid.labels, held.grid.labels)
    assert [m.name for _, m in again.materials] == [m.name for _, m in held.materials]


def test_fortran_and_c_ordered_npy_and_a_flipped_grid_read_alike(tmp_path, monkeypatch):
    values = np.arange(7 * 5 * 3, dtype=np.int16).reshape(7, 5, 3) % 4
    np.save(tmp_path / "c.npy", np.ascontiguousarray(values))
    np.save(tmp_path / "f.npy", np.asfortranarray(values))
    monkeypatch.setattr(slabs, "SLAB_BYTES", 8)  # a row of 3 or 7 values at a time
    for name in ("c.npy", "f.npy"):
        b = load_bone(tmp_path / name, LoadOptions(kind="labels", spacing_mm=(1, 1, 1)))
        np.testing.assert_array_equal(b.grid.labels > 0, values > 0)
    npz = tmp_path / "flipped.npz"
    np.savez(npz, labels=np.asfortranarray(values), spacing_mm=[1.0],
             direction=np.diag([-1.0, 1.0, 1.0]))
    b = load_bone(npz)
    assert any("left-handed" in n for n in b.notes)
    np.testing.assert_array_equal(b.grid.labels > 0, values[::-1] > 0)


def test_a_bone_over_the_budget_is_refused_from_the_header(tmp_path):
    np.save(tmp_path / "v.npy", np.zeros((64, 64, 64), dtype=np.uint8))
    budget = bone_bytes((64, 64, 64))  # no room for anything beside the bone
    with pytest.raises(BoneTooLarge, match=r"needs \d+ MiB of memory \(a 64×64×64 bone takes "
                                           r"1 MiB\), more than the load budget of 1 MiB") as err:
        load_bone(tmp_path / "v.npy", LoadOptions(spacing_mm=(1, 1, 1),
                                                  memory_budget_bytes=budget))
    assert err.value.budget_bytes == budget and err.value.need_bytes > budget
    # The default budget is the bone plus room to read it: the same file loads.
    assert load_bone(tmp_path / "v.npy", SPACING).grid.shape == (64, 64, 64)


def test_a_float64_ct_is_never_held_whole(tmp_path):
    """A 384³ float64 CT (432 MiB of values, a few hundred kB of gzip) loads in a fresh
    process that grows by less than half its values: the bone (2 bytes a voxel while it is
    made) and a slab."""
    path = write_ct(tmp_path / "ct.nrrd", 384, "nrrd")
    values = 384 ** 3 * 8
    script = (
        "import sys\n"
        "from burrforce.server.bone.loaders import LoadOptions, load_bone\n"
        "def kib(f):\n"
        "    return next(int(l.split()[1]) for l in open('/proc/self/status') "
        "if l.startswith(f))\n"
        "load_bone(sys.argv[1], LoadOptions(kind='ct'))  # compiles, warms\n"
        "before = kib('VmRSS')\n"
        "open('/proc/self/clear_refs', 'w').write('5')\n"
        "bone = load_bone(sys.argv[1], LoadOptions(kind='ct'))\n"
        "print(kib('VmHWM') - before, bone.volumes_mm3()['cortical'])\n")
    done = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    grown_kib, cortical = done.stdout.split()
    assert int(grown_kib) * 1024 < values / 2, grown_kib
    assert float(cortical) == pytest.approx(192 ** 3 * 0.125)


def test_compressed_data_shorter_than_its_header_is_truncated(tmp_path):
    """bzip2 keeps no size: the data ends 4 bytes short of the header's 64 as it inflates."""
    header = (b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: bzip2\n"
              b"space directions: (1,0,0) (0,1,0) (0,0,1)\n\n")
    (tmp_path / "short.nrrd").write_bytes(header + bz2.compress(b"\1" * 60))
    with pytest.raises(BoneFileError, match="truncated: it inflates to 60 bytes where the "
                                            "header declares 64"):
        load_bone(tmp_path / "short.nrrd", LoadOptions(kind="labels"))


def _nifti(tmp_path: Path, **fields) -> Path:
    import nibabel as nib

    image = nib.Nifti1Image(np.ones((3, 3, 3), dtype=np.uint8), None)
    image.header.set_zooms((0.5, 0.5, 0.5))
    path = tmp_path / "x.nii"
    nib.save(image, path)
    raw = bytearray(path.read_bytes())
    for offset, (fmt, value) in fields.items():
        struct.pack_into(fmt, raw, int(offset), value)
    path.write_bytes(bytes(raw))
    return path


def test_a_nifti_header_with_a_bad_dimension_count_is_named_so(tmp_path):
    path = _nifti(tmp_path, **{"40": ("<h", 99)})  # dim[0]
    with pytest.raises(BoneFileError, match=r"not a valid NIfTI header: dim\[0\] \(the number "
                                            r"of dimensions\) is 99, not 1–7"):
        load_bone(path, LoadOptions(kind="labels"))
    path = _nifti(tmp_path, **{"0": ("<i", 1234)})  # sizeof_hdr
    with pytest.raises(BoneFileError, match="sizeof_hdr 1234, not 348"):
        load_bone(path, LoadOptions(kind="labels"))


def test_a_nifti_without_a_voxel_size_is_refused_or_given_one(tmp_path):
    path = _nifti(tmp_path, **{"80": ("<f", 0.0)})  # pixdim[1]; no sform, no qform
    with pytest.raises(BoneFileError, match=r"no voxel size: pixdim\[1:4\] is \[0.0, 0.5, "
                                            r"0.5\].*give spacing_mm"):
        load_bone(path, LoadOptions(kind="labels"))
    bone = load_bone(path, LoadOptions(kind="labels", spacing_mm=(0.25, 0.25, 0.25)))
    np.testing.assert_allclose(bone.grid.spacing_mm, 0.25)
    assert any("no voxel size" in n for n in bone.notes)
