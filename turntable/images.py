"""Reading input images and listing image folders, with errors that name the file.

Every image the project reads goes through :func:`read_image`, which returns
the picture as the camera's owner saw it: BGR uint8 (H, W, 3), upright.

- **Orientation.** Phones store portrait photos as landscape pixels plus an
  EXIF orientation (1-8). For the formats OpenCV decodes (JPEG, PNG, TIFF,
  WebP, BMP) ``cv2.imdecode`` with ``IMREAD_COLOR`` applies it (OpenCV 5.0
  does so for all eight values in all four formats; ``tests/test_images.py``
  pins this, so an OpenCV that stops doing it fails the tests). HEIC/HEIF
  carry the rotation as ``irot``/``imir`` boxes, which libheif applies while
  decoding (through ``pillow-heif``); their EXIF orientation, which phones
  write to match, is not applied a second time.
- **Bit depth.** 16-bit PNG/TIFF (and 10/12-bit HEIF) become 8 bit by scaling,
  ``round(v / 257)`` (65535 -> 255), never by dropping the high byte. The
  values are taken as encoded like 8-bit photos (sRGB-like); a 32-bit float
  image is refused (its range is unknown).
- **Focal length.** :func:`exif_focal_px` turns the EXIF 35 mm equivalent focal
  length into pixels of the image as read (see there for the convention).
"""

from __future__ import annotations

import io
import math
import re
from pathlib import Path

import cv2
import numpy as np

from .errors import UserError

__all__ = ["IMAGE_SUFFIXES", "HEIF_SUFFIXES", "read_image", "read_alpha", "list_images", "natural_key",
           "exif_focal_35mm", "exif_focal_px", "focal_px_from_35mm", "FULL_FRAME_DIAGONAL_MM",
           "FOCAL_DISAGREE_REL", "exif_focal_report", "focal_warning"]

HEIF_SUFFIXES = {".heic", ".heif", ".hif"}
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"} | HEIF_SUFFIXES

#: Diagonal of the 36 x 24 mm frame that "35 mm equivalent" focal lengths refer to.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # 43.267 mm

_HEIF_BRANDS = {b"heic", b"heix", b"hevc", b"hevx", b"heim", b"heis", b"hevm", b"hevs", b"mif1", b"msf1"}
_EXIF_IFD = 0x8769
_TAG_FOCAL_35MM = 0xA405  # FocalLengthIn35mmFilm, mm (integer)

#: Calibrated and EXIF focal lengths further apart than this (relative) are reported.
FOCAL_DISAGREE_REL = 0.05


def natural_key(name: str) -> list:
    """Sort key so that ``frame_2`` comes before ``frame_10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _is_heif(data: bytes) -> bool:
    """An ISO-BMFF ``ftyp`` box whose major or compatible brands name HEIF/HEVC images."""
    if len(data) < 16 or data[4:8] != b"ftyp":
        return False
    size = int.from_bytes(data[:4], "big")
    box = data[8:min(max(size, 16), len(data), 256)]
    brands = {box[i:i + 4] for i in range(0, len(box) - 3, 4)}
    return bool(brands & _HEIF_BRANDS) and not brands & {b"avif", b"avis"}  # AVIF: no decoder here


def _decode_heif(data: bytes, path: Path) -> np.ndarray:
    """RGB(A) uint8/uint16 pixels of the primary image, ``irot``/``imir`` applied by libheif."""
    try:
        import pillow_heif
    except ImportError:
        raise UserError(f"{path}: HEIC/HEIF images need the pillow-heif package "
                        f"(pip install pillow-heif)") from None
    try:
        heif = pillow_heif.open_heif(io.BytesIO(data), convert_hdr_to_8bit=False)
        rgb = np.asarray(heif)
    except Exception as exc:  # libheif reports truncation and corruption as ValueError/RuntimeError
        raise UserError(f"{path}: cannot decode HEIC/HEIF image ({exc})") from None
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    return np.ascontiguousarray(rgb[..., 2::-1])  # RGB(A) -> BGR, alpha dropped


def _to_bgr8(img: np.ndarray, path: Path) -> np.ndarray:
    """BGR uint8 (H, W, 3) from what a decoder gave: 16 bit scaled by 1/257, rounded."""
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.ndim != 3 or img.shape[2] != 3:
        raise UserError(f"{path}: unsupported image layout {img.shape} (expected colour or grey)")
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        # round(v / 257): 0 -> 0, 65535 -> 255; never a wrap-around or a dropped high byte
        return cv2.convertScaleAbs(img, alpha=1.0 / 257.0)
    raise UserError(f"{path}: {img.dtype} pixels are not supported (the range of such images is not "
                    f"defined); save the photos as 8- or 16-bit")


#: Photos larger than this are refused from their header, before decoding (a 20000 x 20000 PNG
#: would take 1.2 GB as BGR, and far more in the stages); 100 MP medium-format photos still pass.
MAX_PIXELS = 150_000_000


def _check_pixel_count(data: bytes, path: Path) -> None:
    """``UserError`` when the image's header says it has more than :data:`MAX_PIXELS` pixels.

    The size comes from the header only (Pillow reads it lazily; for HEIF the
    container's primary image). Files Pillow cannot parse are left to the decoder.
    """
    import warnings

    from PIL import Image

    size = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            if _is_heif(data):
                import pillow_heif

                size = pillow_heif.open_heif(io.BytesIO(data)).size
            else:
                with Image.open(io.BytesIO(data)) as im:
                    size = im.size
    except Image.DecompressionBombError as exc:  # Pillow's own limit (about 179 MP) stops the header read
        n = re.search(r"\((\d+) pixels\)", str(exc))
        what = f"{int(n.group(1)) / 1e6:.0f} MP" if n else "the image"
        raise UserError(f"{path}: {what} is more than turntable reads ({MAX_PIXELS / 1e6:.0f} MP); "
                        f"downscale the photos first") from None
    except Exception:  # not something Pillow parses: the decoder will say what is wrong
        return
    if size is not None and size[0] * size[1] > MAX_PIXELS:
        raise UserError(f"{path}: {size[0]}x{size[1]} pixels ({size[0] * size[1] / 1e6:.0f} MP) is more than "
                        f"turntable reads ({MAX_PIXELS / 1e6:.0f} MP); downscale the photos first")


def read_image(path: str | Path) -> np.ndarray:
    """An image file as BGR uint8 (H, W, 3), upright (EXIF orientation / HEIF rotation applied).

    JPEG, PNG, TIFF, WebP, BMP (8 or 16 bit) and HEIC/HEIF; 16-bit values are
    scaled to 8 bit (``round(v / 257)``). See the module docstring.

    Raises
    ------
    UserError
        The file is missing, is a folder, cannot be read or decoded, or has
        pixels of an unsupported type; the message names the file and the reason.
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: file not found")
    if path.is_dir():
        raise UserError(f"{path}: is a folder, not an image")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise UserError(f"{path}: cannot read file ({exc.strerror or exc})") from None
    _check_pixel_count(data, path)
    if _is_heif(data):
        img = _decode_heif(data, path)
    else:
        buf = np.frombuffer(data, dtype=np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH) if buf.size else None
        if img is None:
            if path.suffix.lower() in HEIF_SUFFIXES:
                raise UserError(f"{path}: cannot decode image (named {path.suffix}, but its content is neither "
                                f"HEIC/HEIF nor another image format)")
            raise UserError(f"{path}: cannot decode image (not an image file, or corrupt)")
    return _to_bgr8(img, path)


def read_alpha(path: str | Path) -> np.ndarray | None:
    """The transparency of an image file as uint8 (H, W), upright, or None where it has none.

    None unless the file carries an alpha channel (or a palette/colour key
    transparency) with some pixel less than opaque and some more than
    transparent: a cut-out (a background remover's PNG, the object on
    transparent pixels) has one, a plain black-and-white mask has not. The
    header is read first (Pillow opens lazily), so a file without transparency
    is not decoded here. Upright as :func:`read_image` gives the colours: the
    EXIF orientation is applied. A file larger than :data:`MAX_PIXELS` is
    refused from its header, as by :func:`read_image`; one that cannot be read
    gives None (:func:`read_image` says why).
    """
    import warnings

    from PIL import Image, ImageOps

    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError:
        return None
    _check_pixel_count(data, path)
    if _is_heif(data):
        return None  # HEIF masks: no transparency read here
    try:
        with warnings.catch_warnings(), Image.open(io.BytesIO(data)) as im:
            warnings.simplefilter("ignore")
            if not (im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info):
                return None
            rgba = ImageOps.exif_transpose(im).convert("RGBA")
    except (OSError, ValueError, Image.DecompressionBombError):
        return None  # not an image Pillow reads (read_image says why, if it cannot either)
    a = np.asarray(rgba)[..., 3]
    # all opaque: a plain image; all transparent: no picture at all, the colours are what was meant
    return None if a.min() == 255 or a.max() == 0 else np.ascontiguousarray(a)


def list_images(folder: str | Path) -> list[Path]:
    """Image files of ``folder`` in natural order; ``UserError`` if none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"{folder}: not a folder")
    files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise UserError(f"{folder}: no images found (looked for {', '.join(sorted(IMAGE_SUFFIXES))})")
    return files


# --------------------------------------------------------------------------- EXIF focal length
def _exif_of(path: Path):
    """The file's EXIF as a ``PIL.Image.Exif`` (empty when it has none); None if unreadable."""
    from PIL import Image

    try:
        with path.open("rb") as fh:
            head = fh.read(256)
        if _is_heif(head):
            import pillow_heif

            raw = pillow_heif.open_heif(str(path)).info.get("exif")
            exif = Image.Exif()
            if raw:
                exif.load(raw)
            return exif
        with Image.open(path) as im:  # lazy: reads the header, not the pixels
            return im.getexif()
    except Exception:  # EXIF is optional information: an odd file simply has none
        return None


def exif_focal_35mm(path: str | Path) -> float | None:
    """EXIF ``FocalLengthIn35mmFilm`` of an image file, mm; None when absent, zero or unreadable."""
    exif = _exif_of(Path(path))
    if exif is None:
        return None
    try:
        value = exif.get_ifd(_EXIF_IFD).get(_TAG_FOCAL_35MM, exif.get(_TAG_FOCAL_35MM))
        f35 = float(value) if value is not None else 0.0
    except (TypeError, ValueError, KeyError):
        return None
    return f35 if math.isfinite(f35) and f35 > 0 else None


def focal_px_from_35mm(f35_mm: float, width: int, height: int) -> float:
    """Focal length in pixels from a 35 mm equivalent focal length (diagonal convention).

    ``f_px = f35 / 43.267 mm * sqrt(W^2 + H^2)``: the equivalent focal length
    gives the same diagonal field of view on the 36 x 24 mm frame (diagonal
    43.267 mm) as the real lens on the real sensor, so the image diagonal in
    pixels plays the part of 43.267 mm. This holds for any aspect ratio (a 4:3
    phone image is not 36 mm wide at equivalent scale) and does not depend on
    the orientation. It assumes the image is the whole sensor frame, unscaled
    or scaled uniformly (a crop changes the diagonal and breaks it).
    """
    if not (f35_mm > 0 and width > 0 and height > 0):
        raise ValueError(f"expected positive f35, width, height, got {f35_mm}, {width}, {height}")
    return float(f35_mm) / FULL_FRAME_DIAGONAL_MM * math.hypot(width, height)


def exif_focal_px(path: str | Path, width: int, height: int) -> float | None:
    """The EXIF 35 mm equivalent focal length of ``path`` in pixels of a ``width`` x ``height`` image.

    None when the file has no usable ``FocalLengthIn35mmFilm``. The EXIF
    ``FocalLength`` in mm is not used: turning it into pixels needs the sensor
    size, which phones do not record reliably (``FocalPlaneXResolution`` refers
    to the sensor read-out, not to the stored, often binned or cropped, image).
    """
    f35 = exif_focal_35mm(path)
    return None if f35 is None else focal_px_from_35mm(f35, width, height)


def exif_focal_report(paths, width: int, height: int, focal_calibrated_px: float) -> dict | None:
    """The photos' EXIF focal length against the calibrated one; None when no photo has one.

    Parameters
    ----------
    paths : list of path
        The photos (their EXIF headers are read, not their pixels).
    width, height : int
        Size of the images as read (upright), pixels.
    focal_calibrated_px : float
        The calibrated focal length, pixels.

    Returns
    -------
    dict or None
        ``focal_35mm`` (median over the photos that have one), ``focal_px``,
        ``photos`` (how many have one), ``calibrated_vs_exif_pct``
        (100 (f_cal / f_exif - 1)), ``disagrees`` (beyond
        :data:`FOCAL_DISAGREE_REL`), and ``note`` when the photos' values differ.
    """
    f35 = [v for v in (exif_focal_35mm(p) for p in paths) if v is not None]
    if not f35:
        return None
    f35_mm = float(np.median(f35))
    f_exif = focal_px_from_35mm(f35_mm, width, height)
    rel = float(focal_calibrated_px) / f_exif - 1.0
    report = {"focal_35mm": f35_mm, "focal_px": round(f_exif, 2), "photos": len(f35),
              "calibrated_vs_exif_pct": round(100.0 * rel, 2), "disagrees": bool(abs(rel) > FOCAL_DISAGREE_REL)}
    if len(set(f35)) > 1:
        report["note"] = (f"the photos' EXIF focal lengths differ ({', '.join(f'{v:g}' for v in sorted(set(f35)))} "
                          f"mm equivalent): was the zoom changed between photos?")
    return report


def focal_warning(focal_calibrated_px: float, report: dict | None) -> str | None:
    """The line to print when calibration and EXIF disagree by more than 5 %; None otherwise."""
    if report is None or not report["disagrees"]:
        return None
    return (f"calibrated focal length {focal_calibrated_px:.1f} px and the EXIF focal length "
            f"({report['focal_35mm']:g} mm equivalent = {report['focal_px']:.1f} px) disagree by "
            f"{report['calibrated_vs_exif_pct']:+.1f} % (more than {100 * FOCAL_DISAGREE_REL:.0f} %): check that "
            f"--r-outer/--r-inner are the radii printed on the sheet and that the photos are neither cropped "
            f"nor digitally zoomed")
