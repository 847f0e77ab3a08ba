"""Decode and validate encoded frames: size limits, dimensions read from the header before
the pixels are decoded, then OpenCV decoding to 8-bit grayscale."""

from __future__ import annotations

import struct

import cv2
import numpy as np

from service.api.errors import BadRequest, PayloadTooLarge, UnsupportedMediaType

MEDIA_TYPES = {"image/png": "png", "image/jpeg": "jpeg", "image/jpg": "jpeg"}
_PNG_SIG = b"\x89PNG\r\n\x1a\n"


def sniff_format(data: bytes) -> str | None:
    if data.startswith(_PNG_SIG):
        return "png"
    if data.startswith(b"\xff\xd8"):
        return "jpeg"
    return None


def header_size(data: bytes, fmt: str) -> tuple[int, int]:
    """(width, height) from the PNG IHDR or the JPEG SOF marker, without decoding pixels."""
    if fmt == "png":
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise BadRequest("PNG header is truncated or has no IHDR chunk")
        w, h = struct.unpack(">II", data[16:24])
        return w, h
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise BadRequest(f"JPEG marker expected at byte {i}; the file is corrupted")
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        if marker == 0xFF:
            i += 1
            continue
        (seg_len,) = struct.unpack(">H", data[i + 2 : i + 4])
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > len(data):
                break
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return w, h
        i += 2 + seg_len
    raise BadRequest("JPEG has no frame header (SOF); the file is truncated or corrupted")


def check_size(w: int, h: int, max_pixels: int, min_side: int) -> None:
    """The size limits of every frame, encoded or raw (ROS 2 sensor_msgs/Image)."""
    if w < min_side or h < min_side:
        raise BadRequest(f"image is {w}x{h} pixels; frames need at least {min_side}x{min_side} "
                         "pixels to carry features")
    if w * h > max_pixels:
        raise PayloadTooLarge(f"image is {w}x{h} = {w * h} pixels; the limit is {max_pixels}")


def decode_frame(data: bytes, content_type: str | None, max_bytes: int, max_pixels: int,
                 min_side: int = 1) -> np.ndarray:
    """Validated 8-bit grayscale image, or a ServiceError saying what is wrong.

    A JPEG's EXIF orientation is applied (as every camera app shows the photo), so the
    decoded image may be the header's size turned by 90 degrees."""
    if len(data) > max_bytes:
        raise PayloadTooLarge(f"frame is {len(data)} bytes; the limit is {max_bytes} bytes")
    if not data:
        raise BadRequest("empty body: send a PNG or JPEG image")
    ctype = (content_type or "").split(";")[0].strip().lower()
    if ctype and ctype not in MEDIA_TYPES and ctype != "application/octet-stream":
        raise UnsupportedMediaType(
            f"content type '{ctype}' is not supported; send image/png or image/jpeg")
    fmt = sniff_format(data)
    if fmt is None:
        raise BadRequest("body is neither a PNG nor a JPEG image (unknown signature)")
    if ctype in MEDIA_TYPES and MEDIA_TYPES[ctype] != fmt:
        raise BadRequest(f"content type says {ctype} but the body is a {fmt.upper()} image")
    w, h = header_size(data, fmt)
    check_size(w, h, max_pixels, min_side)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise BadRequest(f"the {fmt.upper()} image could not be decoded (corrupted data)")
    if img.shape != (h, w) and not (fmt == "jpeg" and img.shape == (w, h)):
        raise BadRequest(f"decoded size {img.shape[::-1]} differs from the header {w}x{h}")
    return img


def encode_png(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()
