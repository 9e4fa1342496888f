"""Camera images and video as 8-bit luminance: PNG and EXR files, zips of image sequences,
and video files decoded with OpenCV (the inputs of performance-flow tracking, fyffe,
digital_ira_course2014 §3: "frames per view").

Every reader returns (H,W) or (T,H,W) ``uint8`` sRGB-encoded luminance, the form the
tracking's flows work on (:mod:`service.methods.tracking`): a colour image becomes its
Rec. 709 luminance; 16-bit PNG is scaled to 8 bits; an EXR's linear values (``Y``, or
``R``, ``G``, ``B``) are sRGB-encoded. Malformed input raises
:class:`~service.io.errors.FormatError` naming the file; counts and pixel totals are bounded
before decoding (:class:`~service.io.errors.SizeLimitError`).
"""

from __future__ import annotations

import os
import re
import zipfile
from pathlib import Path, PurePosixPath
from typing import BinaryIO

import numpy as np

from service.io.errors import FormatError, SizeLimitError
from service.io.exr import read_exr

#: image file suffixes accepted in sequences
IMAGE_SUFFIXES = (".png", ".exr")
#: video file suffixes decoded with OpenCV
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".avi", ".mkv", ".webm", ".mpg", ".mpeg")
#: most pixels of one image
MAX_PIXELS = 4096 * 4096
#: most frames of one view
MAX_FRAMES = 100_000
#: Rec. 709 luminance weights (R, G, B)
LUMA = np.array([0.2126, 0.7152, 0.0722])


def srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear luminance (…) in [0,1] → 8-bit sRGB-encoded ``uint8`` (values clipped)."""
    y = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    s = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
    return np.rint(255 * s).astype(np.uint8)


def _luminance(image: np.ndarray, name: str) -> np.ndarray:
    """A decoded OpenCV image (H,W), (H,W,2|3|4) uint8/uint16 → (H,W) uint8."""
    if image.dtype == np.uint16:
        image = (image.astype(np.float64) / 257.0)
    elif image.dtype != np.uint8:
        raise FormatError(f"{name}: {image.dtype} pixels are not supported (8- or 16-bit PNG)")
    if image.ndim == 3:
        if image.shape[2] in (1, 2):
            image = image[..., 0]
        elif image.shape[2] in (3, 4):           # OpenCV decodes to BGR(A)
            image = image[..., 2::-1][..., :3].astype(np.float64) @ LUMA
        else:
            raise FormatError(f"{name}: {image.shape[2]} channels (expected 1 to 4)")
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def decode_image(data: bytes, name: str) -> np.ndarray:
    """A PNG or EXR file's content → (H,W) uint8 luminance (the type from ``name``'s suffix)."""
    suffix = PurePosixPath(name).suffix.lower()
    if suffix == ".exr":
        channels = read_exr(data, max_texels=MAX_PIXELS)
        if "Y" in channels:
            linear = channels["Y"]
        elif {"R", "G", "B"} <= set(channels):
            linear = np.stack([channels[c] for c in "RGB"], axis=-1) @ LUMA
        else:
            raise FormatError(f"{name}: an EXR image needs a 'Y' channel or 'R', 'G', 'B' "
                              f"(it has {sorted(channels)})")
        if not np.isfinite(linear).all():
            raise FormatError(f"{name}: the EXR has NaN or infinite pixels")
        return srgb8(linear)
    if suffix != ".png":
        raise FormatError(f"{name}: unsupported image type {suffix or '(no suffix)'!r}; "
                          f"expected {' or '.join(IMAGE_SUFFIXES)}")
    raw = np.frombuffer(data, np.uint8)
    if len(raw) < 24 or raw[:8].tobytes() != b"\x89PNG\r\n\x1a\n":
        raise FormatError(f"{name}: not a PNG file")
    if raw[12:16].tobytes() != b"IHDR":
        raise FormatError(f"{name}: a damaged PNG (no IHDR header chunk)")
    width, height = int.from_bytes(raw[16:20].tobytes(), "big"), int.from_bytes(raw[20:24].tobytes(), "big")
    if width * height > MAX_PIXELS:
        raise SizeLimitError(f"pixels ({name}: {width}×{height})", width * height, MAX_PIXELS)
    import cv2   # here, not at import: the API imports this module (issue 23's cold start)

    image = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FormatError(f"{name}: the PNG could not be decoded (damaged?)")
    return _luminance(image, name)


def _natural_key(name: str) -> list:
    """Sort key putting ``frame_2`` before ``frame_10``."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def image_zip(source: str | os.PathLike | BinaryIO, what: str,
              max_images: int = MAX_FRAMES) -> dict[str, list[tuple[str, bytes]]]:
    """The images (PNG/EXR) of a zip grouped by folder: folder → [(file stem, bytes)], each
    group in natural name order (``frame_2`` before ``frame_10``). Files at the top level
    are the group ``""``; hidden files, ``__MACOSX`` and folders are skipped; other files
    are a FormatError. Only one folder level is read (``view/frame.png``).
    """
    try:
        archive = zipfile.ZipFile(source)
    except (zipfile.BadZipFile, OSError) as error:
        raise FormatError(f"{what} is not a readable zip file ({error})") from None
    groups: dict[str, list[tuple[str, bytes]]] = {}
    with archive:
        infos = [i for i in archive.infolist() if not i.is_dir()
                 and not any(p.startswith((".", "__MACOSX")) for p in PurePosixPath(i.filename).parts)]
        if len(infos) > max_images:
            raise SizeLimitError(f"files ({what})", len(infos), max_images)
        for info in infos:
            path = PurePosixPath(info.filename)
            if path.suffix.lower() not in IMAGE_SUFFIXES:
                raise FormatError(f"{what}: {info.filename!r} is not an image (expected "
                                  f"{', '.join(IMAGE_SUFFIXES)} files)")
            if len(path.parts) > 2:
                raise FormatError(f"{what}: {info.filename!r} is nested too deep (expected "
                                  "folder/image or image)")
            if info.file_size > 4 * MAX_PIXELS * 4 + (1 << 20):
                raise SizeLimitError(f"bytes ({what}: {info.filename!r} decompressed)",
                                     info.file_size, 16 * MAX_PIXELS + (1 << 20))
            folder = path.parts[0] if len(path.parts) == 2 else ""
            try:
                data = archive.read(info)
            except (zipfile.BadZipFile, OSError, EOFError) as error:
                raise FormatError(f"{what}: {info.filename!r} cannot be read ({error})") from None
            groups.setdefault(folder, []).append((path.name, data))
    for folder in groups:
        groups[folder].sort(key=lambda item: _natural_key(item[0]))
    return groups


def decode_sequence(files: list[tuple[str, bytes]], what: str) -> np.ndarray:
    """Images [(name, bytes)] → (T,H,W) uint8, all of one size (a FormatError naming the
    first that differs)."""
    frames = []
    for name, data in files:
        image = decode_image(data, f"{what}/{name}")
        if frames and image.shape != frames[0].shape:
            raise FormatError(f"{what}: {name!r} is {image.shape[1]}×{image.shape[0]} pixels, "
                              f"the first image {frames[0].shape[1]}×{frames[0].shape[0]}")
        frames.append(image)
    return np.stack(frames)


def read_video(path: str | os.PathLike, what: str, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """Every frame of a video file, decoded with OpenCV's ``cv2.VideoCapture`` → (T,H,W)
    uint8 luminance. FormatError if OpenCV cannot open it or it has no frames."""
    import cv2   # here, not at import: the API imports this module (issue 23's cold start)

    capture = cv2.VideoCapture(str(Path(path)))
    try:
        if not capture.isOpened():
            raise FormatError(f"{what}: OpenCV cannot decode this video (unknown container "
                              "or codec, or not a video)")
        frames = []
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if frame.shape[0] * frame.shape[1] > MAX_PIXELS:
                raise SizeLimitError(f"pixels per frame ({what})",
                                     frame.shape[0] * frame.shape[1], MAX_PIXELS)
            if len(frames) >= max_frames:
                raise SizeLimitError(f"frames ({what})", len(frames) + 1, max_frames)
            frames.append(_luminance(frame, what))
    finally:
        capture.release()
    if not frames:
        raise FormatError(f"{what}: the video has no decodable frames")
    return np.stack(frames)
