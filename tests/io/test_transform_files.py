"""ITK transform files: round trips, SimpleITK as independent reference, Slicer's conventions."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import SimpleITK as sitk

from comreg_core.errors import (
    ComRegError,
    CorruptFileError,
    InputFileNotFoundError,
    InvalidTransformError,
    UnsupportedFormatError,
)
from comreg_core.io import transform_files as tf
from comreg_core.io.transform_files import (
    load_transform,
    read_itk_transform,
    save_transform,
    write_itk_transform,
)
from comreg_core.transforms import T_RAS_LPS, apply_transform
from tests.helpers import assert_close, random_rigid

EXTS = [".tfm", ".txt", ".h5", ".hdf5"]


def _random_affine(rng):
    T = random_rigid(rng)
    T[:3, :3] = T[:3, :3] @ np.array([[1.2, 0.1, 0.0], [0.0, 0.9, -0.2], [0.05, 0.0, 1.1]])
    return T


def _sitk_points(transform, points):
    return np.array([transform.TransformPoint(tuple(map(float, p))) for p in points])


def _write_tfm(path, body):
    path.write_text("#Insight Transform File V1.0\n#Transform 0\n" + body)
    return path


# ---------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("ext", EXTS)
def test_save_load_round_trip_rigid_and_affine(tmp_path, ext):
    rng = np.random.default_rng(1)
    for i, T in enumerate([random_rigid(rng), _random_affine(rng)]):
        path = tmp_path / f"t{i}{ext}"
        assert save_transform(T, path) == path
        assert_close(load_transform(path), T, atol=1e-12, what="loaded T_ct_us")
        raw = read_itk_transform(path)
        assert raw.transform_type == "AffineTransform_double_3_3"
        assert raw.components == ()
        assert_close(raw.matrix, np.linalg.inv(T), atol=1e-12, what="file holds inv(T)")


@pytest.mark.parametrize("ext", [".tfm", ".h5"])
def test_write_itk_transform_is_verbatim(tmp_path, ext):
    M = _random_affine(np.random.default_rng(2))
    path = write_itk_transform(M, tmp_path / f"m{ext}")
    assert_close(read_itk_transform(path).matrix, M, atol=0.0, what="raw matrix")


def test_text_layout_is_what_slicer_writes(tmp_path):
    M = np.eye(4)
    M[:3, 3] = [1.5, -2.0, 0.1]
    write_itk_transform(M, tmp_path / "m.tfm")
    assert (tmp_path / "m.tfm").read_text() == (
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 1.5 -2 0.1\nFixedParameters: 0 0 0\n")


def test_ras_lps_conversion(tmp_path):
    T = random_rigid(np.random.default_rng(3))
    path = tmp_path / "ras.tfm"
    save_transform(T, path, space="RAS")
    assert_close(load_transform(path, space="LPS"), T_RAS_LPS @ T @ T_RAS_LPS, atol=1e-12,
                 what="LPS view of a RAS transform")
    assert_close(load_transform(path, space="ras"), T, atol=1e-12, what="RAS round trip")
    assert_close(read_itk_transform(path).matrix, np.linalg.inv(T_RAS_LPS @ T @ T_RAS_LPS),
                 atol=1e-12, what="Slicer's file formula")


# ------------------------------------------------------------- SimpleITK as independent reference


@pytest.mark.parametrize("ext", [".tfm", ".h5"])
def test_sitk_reads_ours_in_resampling_direction(tmp_path, ext):
    rng = np.random.default_rng(4)
    T_ct_us = random_rigid(rng)
    path = save_transform(T_ct_us, tmp_path / f"us_to_ct{ext}")
    p_ct = rng.uniform(-150, 150, (20, 3))
    # ITK maps fixed (CT) points to moving (US) points: inv(T_ct_us).
    expected_us = apply_transform(np.linalg.inv(T_ct_us), p_ct)
    assert_close(_sitk_points(sitk.ReadTransform(str(path)), p_ct), expected_us, atol=1e-9,
                 what="SimpleITK TransformPoint")


def _euler(zyx: bool):
    t = sitk.Euler3DTransform((10.0, -20.0, 30.0), 0.3, -0.5, 1.1, (4.0, 5.0, -6.0))
    t.SetComputeZYX(zyx)
    return t


def _affine():
    t = sitk.AffineTransform(3)
    t.SetMatrix([1.1, 0.2, -0.1, 0.05, 0.9, 0.3, -0.2, 0.1, 1.3])
    t.SetTranslation((3.0, -7.0, 11.0))
    t.SetCenter((25.0, -40.0, 60.0))
    return t


def _versor():
    return sitk.VersorRigid3DTransform((0.1, -0.3, 0.2, float(np.sqrt(1 - 0.14))),
                                       (8.0, 9.0, -10.0), (-5.0, 15.0, 33.0))


def _similarity():
    return sitk.Similarity3DTransform(1.3, (0.2, 0.1, -0.4), 0.7, (1.0, 2.0, 3.0), (4.0, 5.0, 6.0))


def _scale_versor():
    t = sitk.ScaleVersor3DTransform((1.2, 0.8, 1.5), (0.1, 0.2, 0.3), 0.4, (1.0, 2.0, 3.0))
    t.SetCenter((7.0, -8.0, 9.0))
    return t


SITK_BUILDERS = {
    "affine_centred": _affine,
    "euler_zxy_centred": lambda: _euler(False),
    "euler_zyx_centred": lambda: _euler(True),
    "versor_rigid": _versor,
    "translation": lambda: sitk.TranslationTransform(3, (1.5, -2.5, 3.5)),
    "similarity": _similarity,
    "scale_versor": _scale_versor,
    "scale": lambda: sitk.ScaleTransform(3, (1.1, 0.9, 1.2)),
    "composite_affine_euler": lambda: sitk.CompositeTransform([_affine(), _euler(False)]),
    "composite_three": lambda: sitk.CompositeTransform(
        [_versor(), sitk.TranslationTransform(3, (1.0, 2.0, 3.0)), _affine()]),
}


@pytest.mark.parametrize("ext", [".tfm", ".h5"])
@pytest.mark.parametrize("name", sorted(SITK_BUILDERS))
def test_ours_reads_sitk_files(tmp_path, ext, name):
    transform = SITK_BUILDERS[name]()
    path = tmp_path / f"{name}{ext}"
    sitk.WriteTransform(transform, str(path))
    ours = read_itk_transform(path)
    points = np.random.default_rng(5).uniform(-200, 200, (20, 3))
    assert_close(apply_transform(ours.matrix, points), _sitk_points(transform, points), atol=1e-9,
                 what=f"{name} point mapping")
    if name.startswith("composite"):
        assert ours.transform_type == "CompositeTransform_double_3_3"
        assert len(ours.components) == transform.GetNumberOfTransforms()


HAND_WRITTEN = {
    "quaternion_unnormalised": ("QuaternionRigidTransform_double_3_3", "0.2 0.4 0.6 1.8 1 2 3",
                                "4 5 6"),
    "versor_rotation_only": ("VersorTransform_double_3_3", "0.1 0.2 0.3", "4 5 6"),
    "matrix_offset_base": ("MatrixOffsetTransformBase_double_3_3",
                           "1 0.1 0 0 2 0 0.2 0 1 1 2 3", "4 5 6"),
    "affine_float": ("AffineTransform_float_3_3", "0 -1 0 1 0 0 0 0 1 1 2 3", "4 5 6"),
    "euler_old_3_fixed": ("Euler3DTransform_double_3_3", "0.3 -0.2 0.1 1 2 3", "4 5 6"),
    "identity": ("IdentityTransform_double_3_3", "", ""),
}


@pytest.mark.parametrize("name", sorted(HAND_WRITTEN))
def test_ours_matches_sitk_on_hand_written_text(tmp_path, name):
    ttype, params, fixed = HAND_WRITTEN[name]
    path = _write_tfm(tmp_path / f"{name}.tfm",
                      f"Transform: {ttype}\nParameters: {params}\nFixedParameters: {fixed}\n")
    points = np.random.default_rng(6).uniform(-100, 100, (10, 3))
    assert_close(apply_transform(read_itk_transform(path).matrix, points),
                 _sitk_points(sitk.ReadTransform(str(path)), points), atol=1e-9, what=name)


def test_rigid3d_matrix_form_equals_matrix_offset_base(tmp_path):
    """SimpleITK cannot read Rigid3DTransform (not in ITK's factory); it has the same
    parameters as MatrixOffsetTransformBase, which SimpleITK can read."""
    body = "Parameters: 0 -1 0 1 0 0 0 0 1 1 2 3\nFixedParameters: 4 5 6\n"
    rigid = _write_tfm(tmp_path / "r.tfm", "Transform: Rigid3DTransform_double_3_3\n" + body)
    base = _write_tfm(tmp_path / "b.tfm",
                      "Transform: MatrixOffsetTransformBase_double_3_3\n" + body)
    points = np.random.default_rng(7).uniform(-100, 100, (10, 3))
    assert_close(apply_transform(read_itk_transform(rigid).matrix, points),
                 _sitk_points(sitk.ReadTransform(str(base)), points), atol=1e-9, what="Rigid3D")


# ------------------------------------------------------------------------ Slicer's convention


@pytest.mark.parametrize(
    "file_params, to_parent_ras",
    [
        ("1 0 0 0 1 0 0 0 1 10 20 -30",
         np.array([[1, 0, 0, 10], [0, 1, 0, 20], [0, 0, 1, 30], [0, 0, 0, 1.0]])),
        ("0 1 0 -1 0 0 0 0 1 20 -10 -30",
         np.array([[0, -1, 0, 10], [1, 0, 0, 20], [0, 0, 1, 30], [0, 0, 0, 1.0]])),
    ],
    ids=["translation", "rot90z_translation"],
)
def test_slicer_written_tfm(tmp_path, file_params, to_parent_ras):
    """What Slicer writes for a transform node whose ToParent (child -> parent, RAS) is known.

    Slicer saves ``inv(T_RAS_LPS @ ToParent_RAS @ T_RAS_LPS)``. For a pure translation of
    (10, 20, 30) mm RAS: in LPS it is (-10, -20, 30) (x and y flip); the file holds the inverse,
    the negated translation (10, 20, -30). With a 90 degree rotation about S (R -> A) as well:
    the rotation about z is the same in LPS, ToParent_LPS = [Rz(90) | (-10, -20, 30)], and the
    file holds [Rz(-90) | -Rz(-90) (-10, -20, 30)] = [Rz(-90) | (20, -10, -30)].
    So load_transform(space="RAS") must give back ToParent_RAS: the transform that moves the
    child (US) into the parent (CT) frame, i.e. T_ct_us.
    """
    path = _write_tfm(tmp_path / "slicer.tfm",
                      f"Transform: AffineTransform_double_3_3\nParameters: {file_params}\n"
                      "FixedParameters: 0 0 0\n")
    assert_close(load_transform(path, space="RAS"), to_parent_ras, atol=1e-12, what="ToParent")
    assert_close(load_transform(path), T_RAS_LPS @ to_parent_ras @ T_RAS_LPS, atol=1e-12,
                 what="ToParent in LPS")
    # The US point at RAS (0, 0, 0) is the CT point at RAS (10, 20, 30); in LPS (-10, -20, 30).
    assert_close(apply_transform(load_transform(path), np.zeros((1, 3))), [[-10, -20, 30]],
                 atol=1e-12, what="origin of the child in the parent, LPS")
    # And saving ToParent_RAS reproduces Slicer's file numbers.
    save_transform(to_parent_ras, tmp_path / "ours.tfm", space="RAS")
    expected = np.array(file_params.split(), dtype=float)
    written = (tmp_path / "ours.tfm").read_text().splitlines()[3].split()[1:]
    assert_close(np.array(written, dtype=float), expected, atol=1e-12, what="written params")


# --------------------------------------------------------------------------------- bad inputs


def test_missing_file_and_wrong_extension(tmp_path):
    with pytest.raises(InputFileNotFoundError):
        load_transform(tmp_path / "nope.tfm")
    (tmp_path / "t.mat").write_text("x")
    with pytest.raises(UnsupportedFormatError, match=r"\.tfm"):
        read_itk_transform(tmp_path / "t.mat")
    with pytest.raises(UnsupportedFormatError):
        save_transform(np.eye(4), tmp_path / "out.mat")
    assert not (tmp_path / "out.mat").exists()


@pytest.mark.parametrize(
    "body, error, match",
    [
        ("hello world, this is not a transform\n", CorruptFileError, "line 3"),
        ("", CorruptFileError, "no 'Transform:'"),
        ("Transform: AffineTransform_double_3_3\nParameters: 1 0 0 0 1 0 0 0 1 1 2\n"
         "FixedParameters: 0 0 0\n", CorruptFileError, "needs 12 Parameters but the file has 11"),
        ("Transform: AffineTransform_double_3_3\nFixedParameters: 0 0 0\n", CorruptFileError,
         "no Parameters"),
        ("Transform: AffineTransform_double_3_3\nParameters: 1 0 0 0 1 0 0 0 1 1 2 abc\n",
         CorruptFileError, "not a number"),
        ("Transform: AffineTransform_double_3_3\nParameters: 1 0 0 0 1 0 0 0 1 1 2 3\n"
         "FixedParameters: 0 0\n", CorruptFileError, "FixedParameters"),
        ("Transform: AffineTransform_double_3_3\nParameters: 1 0 0 0 1 0 0 0 1 nan 2 3\n"
         "FixedParameters: 0 0 0\n", InvalidTransformError, "non-finite"),
        ("Transform: BSplineTransform_double_3_3\nParameters: 0 0 0\nFixedParameters: 0\n",
         InvalidTransformError, "nonlinear"),
        ("Transform: CompositeTransform_double_3_3\n#Transform 1\nTransform: "
         "DisplacementFieldTransform_double_3_3\nParameters: 0\n", InvalidTransformError,
         "nonlinear"),
        ("Transform: FancyTransform_double_3_3\nParameters: 1\n", InvalidTransformError,
         "unsupported transform type"),
        ("Transform: AffineTransform_double_2_2\nParameters: 1 0 0 1 0 0\n",
         InvalidTransformError, "2-D"),
        ("Transform: TranslationTransform_double_3_3\nParameters: 1 2 3\n"
         "Transform: TranslationTransform_double_3_3\nParameters: 1 2 3\n",
         InvalidTransformError, "not wrapped in a CompositeTransform"),
        ("Transform: AffineTransform_double_3_3\nParameters: 1 0 0 0 1 0 0 0 0 1 2 3\n",
         InvalidTransformError, "singular"),
        ("Transform: VersorRigid3DTransform_double_3_3\nParameters: 0.8 0.8 0.8 1 2 3\n",
         InvalidTransformError, "versor has norm"),
    ],
    ids=["garbage", "empty", "truncated", "no_params", "not_number", "bad_fixed", "nan",
         "bspline", "composite_displacement", "unknown", "2d", "two_uncomposed", "singular",
         "versor_norm"],
)
def test_bad_text_content(tmp_path, body, error, match):
    path = _write_tfm(tmp_path / "bad.tfm", body)
    with pytest.raises(error, match=match):
        load_transform(path)


def test_binary_garbage_as_text(tmp_path):
    path = tmp_path / "bin.txt"
    path.write_bytes(bytes(range(256)))
    with pytest.raises(CorruptFileError, match="binary"):
        read_itk_transform(path)


def test_corrupt_h5(tmp_path):
    import h5py

    (tmp_path / "garbage.h5").write_bytes(b"\x89HDF\r\n not really" * 10)
    with pytest.raises(CorruptFileError, match="not a valid HDF5"):
        read_itk_transform(tmp_path / "garbage.h5")
    with h5py.File(tmp_path / "empty.h5", "w") as f:
        f.create_group("Other")
    with pytest.raises(CorruptFileError, match="TransformGroup"):
        read_itk_transform(tmp_path / "empty.h5")
    with h5py.File(tmp_path / "bspline.h5", "w") as f:
        g = f.create_group("TransformGroup/0")
        g.create_dataset("TransformType", data=np.array([b"BSplineTransform_double_3_3"]))
        g.create_dataset("TransformParameters", data=np.zeros(3))
    with pytest.raises(InvalidTransformError, match="nonlinear"):
        read_itk_transform(tmp_path / "bspline.h5")


def test_missing_h5py_gives_install_hint(tmp_path, monkeypatch):
    save_transform(np.eye(4), tmp_path / "ok.h5")
    monkeypatch.setitem(sys.modules, "h5py", None)  # makes `import h5py` raise ImportError
    with pytest.raises(ComRegError, match="pip install h5py"):
        read_itk_transform(tmp_path / "ok.h5")
    with pytest.raises(ComRegError, match="pip install h5py"):
        save_transform(np.eye(4), tmp_path / "new.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.h5"]
    save_transform(np.eye(4), tmp_path / "still_fine.tfm")  # text needs no h5py


def test_invalid_matrix_and_space(tmp_path):
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(InvalidTransformError):
        save_transform(T, tmp_path / "nan.tfm")
    with pytest.raises(ComRegError, match="LPS"):
        save_transform(np.eye(4), tmp_path / "x.tfm", space="XYZ")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("ext", [".tfm", ".h5"])
def test_failed_write_is_atomic(tmp_path, monkeypatch, ext):
    path = tmp_path / f"t{ext}"
    T_old = random_rigid(np.random.default_rng(8))
    save_transform(T_old, path)
    writer = "_write_h5" if ext == ".h5" else "_write_text"
    original = getattr(tf, writer)

    def half_write(tmp, *args):
        original(tmp, *args)
        raise OSError("disk full")

    monkeypatch.setattr(tf, writer, half_write)
    with pytest.raises(OSError, match="disk full"):
        save_transform(np.eye(4), path)
    with pytest.raises(OSError, match="disk full"):
        save_transform(np.eye(4), tmp_path / f"new{ext}")
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]
    monkeypatch.undo()
    assert_close(load_transform(path), T_old, atol=1e-12, what="old file untouched")
