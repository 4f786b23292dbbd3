"""Shared file helpers: compound extensions and atomic writes."""

import pytest

from comreg_core.errors import UnsupportedFormatError
from comreg_core.io._files import atomic_output, file_extension, require_extension


def test_compound_extensions():
    assert file_extension("a/B.Seg.NRRD") == ".seg.nrrd"
    assert file_extension("scan.igs.mha") == ".igs.mha"
    assert file_extension("bone.stl") == ".stl"
    assert require_extension("x.seg.nrrd", "label map", [".nrrd"]) == ".nrrd"
    with pytest.raises(UnsupportedFormatError, match="Use one of: .nrrd"):
        require_extension("x.png", "label map", [".nrrd"])


def test_atomic_output_renames_on_success_and_cleans_up_on_failure(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with atomic_output(target) as tmp:
        assert tmp.parent == target.parent and tmp.name.endswith(".txt")
        tmp.write_text("new")
        assert not target.exists()  # nothing visible until the block succeeds
    assert target.read_text() == "new"
    with pytest.raises(RuntimeError):
        with atomic_output(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert target.read_text() == "new"
    assert [p.name for p in target.parent.iterdir()] == ["out.txt"]
