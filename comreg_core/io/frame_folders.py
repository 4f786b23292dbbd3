"""Frame folders as in UltraBones100k -> :class:`TrackedSweep`: ``frames/<timestamp>.png``,
``tracking.csv`` (probe positions and Euler angles per frame) and ``calibration.json`` (pixel
spacing, image size, image-to-probe pose). Frame conventions: see :mod:`comreg_core.io.sweeps`.
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from comreg_core.transforms import matmul
from comreg_core.errors import ComRegError, CorruptFileError, InputFileNotFoundError
from comreg_core.io._files import file_extension, require_input_file
from comreg_core.io.sweeps import (CalibrationMismatchError, NoValidFramesError, TrackedSweep,
                                   frames_to_grey, parse_float)

log = logging.getLogger(__name__)

#: Image files a frame folder may hold.
FRAME_IMAGE_EXTENSIONS = [".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".pnm"]


@dataclass
class FrameFolderTracking:
    """The poses of a frame folder, from ``tracking.csv`` + ``calibration.json``.

    Attributes:
        names: ``N`` frame names (the ``timestamp`` column as written: the image file stems).
        timestamps_ms: ``(N,)`` the ``timestamp`` column (ms).
        T_ref_image: ``(N, 4, 4)`` image mm -> CT/reference mm (pixel centre ``(c, r)`` at
            ``(c * sx, r * sy, 0)``); rigid.
        spacing: ``(2,)`` ``(sx, sy)`` mm per pixel.
        image_size: ``(W, H)`` px the calibration was made for.
        valid: ``(N,)`` bool, False for rows with non-finite numbers.
    """

    names: list[str]
    timestamps_ms: np.ndarray
    T_ref_image: np.ndarray
    spacing: np.ndarray
    image_size: tuple[int, int]
    valid: np.ndarray


def _euler_pose(translation, euler_xyz_deg) -> np.ndarray:
    """``(..., 4, 4)`` from translations ``(..., 3)`` mm and scipy 'xyz' Euler angles in
    degrees (extrinsic x, then y, then z: ``R = Rz @ Ry @ Rx``)."""
    from scipy.spatial.transform import Rotation

    translation = np.asarray(translation, dtype=np.float64)
    euler = np.asarray(euler_xyz_deg, dtype=np.float64)
    shape = translation.shape[:-1]
    T = np.zeros((*shape, 4, 4))
    T[..., 3, 3] = 1.0
    flat_e = euler.reshape(-1, 3)
    R = np.full((len(flat_e), 3, 3), np.nan)
    good = np.isfinite(flat_e).all(axis=1)
    if good.any():
        R[good] = Rotation.from_euler("xyz", flat_e[good], degrees=True).as_matrix()
    T[..., :3, :3] = R.reshape(*shape, 3, 3)
    T[..., :3, 3] = translation
    return T


@dataclass
class FrameFolderCalibration:
    """A frame folder's ``calibration.json``: ``spacing`` ``(2,)`` mm per pixel ``(sx, sy)``,
    ``image_size`` ``(columns, rows)`` (None when the file does not give it) and
    ``T_probe_image`` ``(4, 4)`` (image mm, pixel centres at ``c + 0.5`` -> probe mm)."""

    spacing: np.ndarray
    image_size: tuple[int, int] | None
    T_probe_image: np.ndarray


def read_frame_folder_calibration(calibration_json: str | Path) -> FrameFolderCalibration:
    """Read and check a ``calibration.json`` (``pixel_spacing_mm``, ``image_to_probe``:
    ``translation_mm`` and ``euler_xyz_deg``, optionally ``image_size_px``); a clear
    :class:`CorruptFileError` otherwise."""
    calibration_json = require_input_file(calibration_json, "calibration file")
    try:
        cal = json.loads(calibration_json.read_text(encoding="utf-8"))
        sx, sy = (float(v) for v in cal["pixel_spacing_mm"])
        size = cal.get("image_size_px")
        size = None if size is None else tuple(int(v) for v in size)
        T_probe_image = _euler_pose(cal["image_to_probe"]["translation_mm"],
                                    cal["image_to_probe"]["euler_xyz_deg"])
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CorruptFileError(calibration_json, f"missing or bad calibration entry ({exc})") \
            from None
    if not (sx > 0 and sy > 0 and np.isfinite([sx, sy]).all()
            and (size is None or (len(size) == 2 and min(size) > 0))
            and np.isfinite(T_probe_image).all()):
        raise CorruptFileError(calibration_json, "pixel spacing, image size and image_to_probe "
                                                 "must be positive, finite numbers")
    return FrameFolderCalibration(np.array([sx, sy]), size, T_probe_image)


def read_frame_folder_tracking(tracking_csv: str | Path, calibration_json: str | Path
                               ) -> FrameFolderTracking:
    """Poses of a frame folder (the one reader of the UltraBones100k tracking chain)::

        p_ref = T_ref_probe(frame) @ T_probe_image @ diag(sx, sy, 1, 1) @ [c + 0.5, r + 0.5, 0, 1]

    (``calibration.json`` counts pixel centres at ``c + 0.5``; ComReg's image frame puts them at
    ``c``, hence a half-pixel shift folded into ``T_ref_image``.) Rows with non-finite values are
    kept as invalid frames, with a warning.
    """
    tracking_csv = require_input_file(tracking_csv, "tracking file")
    cal = read_frame_folder_calibration(calibration_json)
    if cal.image_size is None:
        raise CorruptFileError(calibration_json, "missing or bad calibration entry "
                                                 "('image_size_px')")
    (sx, sy), (cols, rows), T_probe_image = cal.spacing, cal.image_size, cal.T_probe_image
    try:
        with open(tracking_csv, newline="", encoding="utf-8") as f:
            table = list(csv.DictReader(f))
        names = [r["timestamp"].strip() for r in table]
        stamps = np.array([parse_float(r["timestamp"]) for r in table])
        xyz = np.array([[parse_float(r[k]) for k in ("x", "y", "z")] for r in table])
        euler = np.array([[parse_float(r[k]) for k in ("euler_x", "euler_y", "euler_z")]
                          for r in table])
        factors = np.array([parse_float(r.get("space_factor", sx)) for r in table])
    except (KeyError, TypeError, AttributeError, csv.Error, UnicodeDecodeError) as exc:
        raise CorruptFileError(tracking_csv, f"missing or bad tracking column ({exc}); expected "
                                             "timestamp,x,y,z,euler_x,euler_y,euler_z") from None
    if len(stamps) == 0:
        raise CorruptFileError(tracking_csv, "it has no frames")
    valid = np.isfinite(xyz).all(axis=1) & np.isfinite(euler).all(axis=1)
    if (~valid).any():
        log.warning("%s: %d of %d rows have missing or non-numeric pose values; those frames "
                    "are left out", tracking_csv, int((~valid).sum()), len(valid))
    off = np.isfinite(factors) & (np.abs(factors - sx) > 0.01 * sx)
    if off.any():
        log.warning("%s: %d rows give a space_factor (mm per pixel) other than the calibration's "
                    "%.5g mm; the calibration is used", tracking_csv, int(off.sum()), sx)
    T_ref_probe = _euler_pose(np.nan_to_num(xyz), np.nan_to_num(euler))
    half = np.eye(4)
    half[:2, 3] = 0.5 * sx, 0.5 * sy
    T = matmul(matmul(T_ref_probe, T_probe_image), half)
    T[~valid] = np.nan
    return FrameFolderTracking(names, stamps, T, np.array([sx, sy]), (cols, rows), valid)


def read_frame_folder(folder: str | Path, *, calibration: str | Path | None = None,
                      tracking: str | Path | None = None, frames_dir: str | Path | None = None
                      ) -> TrackedSweep:
    """Read a frame folder: images ``frames/<name>.png`` (or beside the CSV), ``tracking.csv``
    and ``calibration.json``; ``<name>`` is the ``timestamp`` column.

    Frames with a tracking row but no image, or an image but no row, are left out with a
    warning; images of another size than the calibration's raise
    :class:`CalibrationMismatchError`.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileNotFoundError(folder, "frame folder")
    if calibration is not None and file_extension(calibration) != ".json":
        raise ComRegError(f"A frame folder needs its calibration as JSON (calibration.json), not "
                          f"'{calibration}'.", "Pass the calibration.json of the recording "
                          "(image_to_probe and pixel_spacing_mm, see the data README).")
    track = read_frame_folder_tracking(tracking or folder / "tracking.csv",
                                       calibration or folder / "calibration.json")
    image_dir = Path(frames_dir) if frames_dir else (folder / "frames" if (folder / "frames")
                                                     .is_dir() else folder)
    files = {p.stem: p for p in sorted(image_dir.iterdir())
             if p.is_file() and p.suffix.lower() in FRAME_IMAGE_EXTENSIONS}
    present = [i for i, name in enumerate(track.names) if name in files]
    missing = [name for name in track.names if name not in files]
    if missing:
        log.warning("%s: %d of %d tracked frames have no image in %s (first: %s); they are "
                    "left out", folder, len(missing), len(track.names), image_dir, missing[0])
    extra = sorted(set(files) - set(track.names))
    if extra:
        log.warning("%s: %d images have no tracking row (first: %s); they are left out", folder,
                    len(extra), files[extra[0]].name)
    if not present:
        raise NoValidFramesError(
            f"No image in '{image_dir}' matches a row of the tracking file (images are named "
            "by the 'timestamp' column, e.g. 162005.png).",
            "Check that the frames and tracking.csv come from the same recording.")
    frames = []
    W, H = track.image_size
    for i in present:
        image = read_frame_image(files[track.names[i]])
        if image.shape != (H, W):
            raise CalibrationMismatchError(
                f"Frame '{files[track.names[i]]}' is {image.shape[1]} x {image.shape[0]} px but "
                f"the calibration is for {W} x {H} px images.",
                "Use the calibration made for this probe and imaging depth, or export the "
                "frames uncropped.")
        frames.append(image)
    idx = np.array(present)
    return TrackedSweep(np.stack(frames), track.spacing, track.T_ref_image[idx],
                        track.timestamps_ms[idx] / 1000.0, track.valid[idx], "CT",
                        [track.names[i] for i in present], folder)


def read_frame_image(path: str | Path) -> np.ndarray:
    """One 2D image file (PNG, JPEG, BMP, TIFF, PNM) as ``(H, W)``, row 0 at the top; colour
    images become luminance, palettes are expanded, alpha is dropped and 1-bit images become
    0/255.

    Decoded by Pillow, which reports a truncated or corrupt file as an error (VTK's readers
    crash on a truncated PNG and fill a truncated JPEG, BMP, TIFF or PNM with garbage): such a
    file raises :class:`CorruptFileError` naming it. PNG files are also checked chunk by chunk
    (lengths and CRCs) before they are decoded.
    """
    path = require_input_file(path, "frame image")
    pixels = _decode_image(path)
    if pixels.ndim not in (2, 3) or pixels.size == 0:
        raise CorruptFileError(path, "the image holds no pixels")
    return np.ascontiguousarray(frames_to_grey(pixels[None])[0])


#: Pillow modes kept as they are (grey, RGB(A), 16/32-bit integer, float); the others become
#: grey ("1", grey + alpha) or RGB (palettes, CMYK, YCbCr, ...).
_KEPT_MODES = ("L", "RGB", "RGBA", "I", "F", "I;16", "I;16L", "I;16B", "I;16N")


def _decode_image(path: Path) -> np.ndarray:
    """``(H, W)`` or ``(H, W, C)`` pixels of one image file, row 0 at the top; every decoding
    failure of Pillow as :class:`CorruptFileError`."""
    import struct
    import warnings
    import zlib

    from PIL import Image, ImageFile, UnidentifiedImageError

    previous = ImageFile.LOAD_TRUNCATED_IMAGES
    ImageFile.LOAD_TRUNCATED_IMAGES = False  # a truncated file must fail, never be padded
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(path) as image:
                if image.format == "PNG":
                    image.verify()  # chunk lengths and CRCs, without decoding
            with Image.open(path) as image:
                if getattr(image, "n_frames", 1) != 1:
                    raise CorruptFileError(path, f"a 2D frame was expected, found "
                                                 f"{image.n_frames} images in one file")
                image.load()
                if image.mode not in _KEPT_MODES:  # alpha is dropped: it is no intensity
                    image = image.convert("L" if image.mode in ("1", "LA", "La") else "RGB")
                pixels = np.asarray(image)
    except (Image.DecompressionBombWarning, Image.DecompressionBombError) as exc:
        raise ComRegError(f"The frame image '{path}' is too large to be an ultrasound frame "
                          f"({' '.join(str(exc).split())})", "Check the image files.") from None
    except UnidentifiedImageError:
        raise CorruptFileError(path, "not a PNG, JPEG, BMP, TIFF or PNM image, or its header "
                                     "is damaged") from None
    except (FileNotFoundError, PermissionError):
        raise
    except (OSError, SyntaxError, ValueError, EOFError, IndexError, TypeError, KeyError,
            struct.error, zlib.error) as exc:  # Pillow's ways of saying 'truncated' or 'broken'
        detail = " ".join(str(exc).split()).rstrip(".") or type(exc).__name__
        raise CorruptFileError(path, f"the image cannot be decoded ({detail})") from None
    finally:
        ImageFile.LOAD_TRUNCATED_IMAGES = previous
    if pixels.dtype.byteorder not in ("=", "|"):
        pixels = pixels.astype(pixels.dtype.newbyteorder("="))
    if pixels.dtype == np.int32 and pixels.size and pixels.min() >= 0 and pixels.max() < 65536:
        pixels = pixels.astype(np.uint16)  # 16-bit grey that Pillow opened as 32-bit 'I'
    return pixels
