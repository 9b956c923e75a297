"""An image's pixel size read from its header, before anything decodes it.

Decoding allocates width x height x channels: a 380 KiB PNG may claim
20000 x 20000 px and cost a worker gigabytes. The API compares the header's
size with the rig's camera first, and decodes only what has the right size.
Only the formats a capture may hold (PNG, JPEG, TIFF) are read; anything
else is refused (OpenCV would decode other formats too, with their own bombs).
"""

import struct

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (C4 is DHT, C8 is reserved, CC is DAC: not frames)
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_TIFF_WIDTH, _TIFF_HEIGHT = 256, 257
_MAX_JPEG_SEGMENTS = 10000  # an endless chain of empty segments is not an image


class HeaderError(ValueError):
    """The header cannot be read: not a PNG, JPEG or TIFF, or cut short."""


def _read(fh, n: int) -> bytes:
    data = fh.read(n)
    if len(data) != n:
        raise HeaderError("the header is cut short")
    return data


def image_size(fh) -> tuple:
    """``(width, height)`` in px from the header of the file ``fh`` (binary, seekable), read from its start."""
    fh.seek(0)
    head = fh.read(8)
    fh.seek(0)
    if head.startswith(PNG_SIGNATURE):
        return _png(fh)
    if head.startswith(b"\xff\xd8"):
        return _jpeg(fh)
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        return _tiff(fh)
    raise HeaderError("not a PNG, JPEG or TIFF file")


def _png(fh) -> tuple:
    data = _read(fh, 8 + 8 + 8)
    length, kind = struct.unpack(">I4s", data[8:16])
    if kind != b"IHDR" or length != 13:
        raise HeaderError("PNG without an IHDR chunk first")
    return struct.unpack(">II", data[16:24])


def _jpeg(fh) -> tuple:
    fh.seek(2)
    for _ in range(_MAX_JPEG_SEGMENTS):
        byte = _read(fh, 1)
        if byte != b"\xff":
            raise HeaderError("JPEG segment does not start with a marker")
        marker = _read(fh, 1)[0]
        while marker == 0xFF:  # fill bytes before a marker
            marker = _read(fh, 1)[0]
        if marker in (0x01,) or 0xD0 <= marker <= 0xD7:  # markers without a length
            continue
        if marker in (0xD9, 0xDA):  # end of image, or the scan before any frame header
            raise HeaderError("JPEG without a frame header before its scan")
        (length,) = struct.unpack(">H", _read(fh, 2))
        if length < 2:
            raise HeaderError("JPEG segment with a bad length")
        if marker in _SOF:
            _precision, height, width = struct.unpack(">BHH", _read(fh, 5))
            return width, height
        fh.seek(length - 2, 1)
    raise HeaderError("JPEG with too many segments before its frame header")


def _tiff(fh) -> tuple:
    """The first image (IFD) of a classic TIFF; BigTIFF is not a capture format."""
    order = "<" if _read(fh, 2) == b"II" else ">"
    (magic, offset) = struct.unpack(order + "HI", _read(fh, 6))
    if magic != 42:
        raise HeaderError("TIFF variant not supported (BigTIFF?)")
    fh.seek(offset)
    (count,) = struct.unpack(order + "H", _read(fh, 2))
    size = {}
    for _ in range(count):
        tag, kind, n, value = struct.unpack(order + "HHI4s", _read(fh, 12))
        if tag in (_TIFF_WIDTH, _TIFF_HEIGHT) and n == 1:
            if kind == 3:  # SHORT
                size[tag] = struct.unpack(order + "H", value[:2])[0]
            elif kind == 4:  # LONG
                size[tag] = struct.unpack(order + "I", value)[0]
    if _TIFF_WIDTH not in size or _TIFF_HEIGHT not in size:
        raise HeaderError("TIFF without its image width and length")
    return size[_TIFF_WIDTH], size[_TIFF_HEIGHT]
