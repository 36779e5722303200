"""Depth, colour and label images and ``.npy``/``.npz`` arrays shared by the capture formats and the
prediction files, each checked against what its header declares before it is decoded, and the one
resize of every image: :func:`resize_nearest` for label ids, depth and masks (values kept),
:func:`resize_bilinear` for colour and class probabilities (Pillow's bilinear).

:func:`open_image` is the one image reader: every image a capture holds (PNG, PGM/PPM, JPEG, TIFF,
any format Pillow reads; a ROS message's compressed bytes too) is opened through it. Pillow reads
the header first; before a pixel is decoded the declared size is checked: at most
:func:`max_pixels` pixels (Pillow's ``Image.MAX_IMAGE_PIXELS``, 89 million: 70 times a 1296x968
colour image), and no more pixel bytes than the file's bytes can hold (raw PGM/PPM/TIFF data: the
bytes themselves; PNG: deflate's 1,032 : 1; TIFF strips: 1,400 : 1, LZW's bound; JPEG: an 8x8
block per 1/8 bit). A file that declares more, is truncated or unreadable is one ValueError naming
it and what was expected (Pillow's own "decompression bomb" error included). :func:`image_size`
reads a header's size alone (the cross-file checks of :mod:`diffuser_lab.data.capture`).
EXR is read by no format (``scene=templates`` refuses ``.exr`` depth with one line)."""
from __future__ import annotations

import io
import math
import re
import threading
import warnings
import zlib
from contextlib import contextmanager
from pathlib import Path
from typing import Union

import numpy as np

from . import inputs

__all__ = ["read_depth_png", "read_rgb", "read_label_png", "label_ids_in", "read_array", "open_image", "image_size",
           "image_complete", "max_pixels", "resize_nearest", "resize_bilinear"]

Source = Union[str, Path, bytes]
"""An image file's path, or an image's bytes (a ROS CompressedImage's)."""


def resize_nearest(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of an (H, W, ...) array to ``shape`` = (H', W').

    Output pixel (r, c) takes input pixel (floor((r + 0.5) H / H'), floor((c + 0.5) W / W')),
    i.e. pixel centres are aligned (the same samples as Pillow's NEAREST). Returns the
    input itself when the shape already matches.
    """
    h, w = img.shape[:2]
    H, W = int(shape[0]), int(shape[1])
    if (h, w) == (H, W):
        return img
    rows = np.minimum(((np.arange(H) + 0.5) * (h / H)).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(W) + 0.5) * (w / W)).astype(np.int64), w - 1)
    return img[rows[:, None], cols[None, :]]


def resize_bilinear(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of an (h, w) or (h, w, C) image to ``shape`` = (H, W): Pillow's BILINEAR, the
    triangle filter with pixel centres aligned (output centre (r + 0.5) h / H - 0.5 in input pixels,
    clamped at the borders) widened by the factor when shrinking (no aliasing); for colour and class
    probabilities (a convex combination: probabilities still sum to one). uint8 with 1 or 3 channels
    in Pillow's 8-bit modes, anything else per channel in float32 (returned as float32). Returns the
    input itself when the shape matches."""
    from PIL import Image

    img = np.asarray(img)
    h, w = img.shape[:2]
    H, W = int(shape[0]), int(shape[1])
    if (h, w) == (H, W):
        return img
    if img.dtype == np.uint8 and (img.ndim == 2 or img.shape[2] in (1, 3)):
        mode = "RGB" if img.ndim == 3 and img.shape[2] == 3 else "L"
        out = np.asarray(Image.fromarray(img.reshape(h, w, -1).squeeze(2) if mode == "L" else img, mode)
                         .resize((W, H), Image.BILINEAR), np.uint8)
        return out.reshape(H, W, *img.shape[2:])
    planes = img.reshape(h, w, -1).astype(np.float32)
    out = np.empty((H, W, planes.shape[2]), np.float32)
    for c in range(planes.shape[2]):  # loop over channels (3 colours, C classes)
        out[..., c] = np.asarray(Image.fromarray(np.ascontiguousarray(planes[..., c]), "F").resize((W, H), Image.BILINEAR))
    return out.reshape(H, W, *img.shape[2:])


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _check_png_chunks(fh, size: int, where: str, what: str) -> None:
    """A PNG's chunk lengths (big-endian uint32 before each chunk's type) against the file's size,
    before Pillow reads them: Pillow reads a chunk it skips at its declared length in one call, so a
    damaged length after the pixels asked for up to 4 GiB (MemoryError, no file named); and each
    chunk's CRC, which Pillow does not check for the pixel data (IDAT): a damaged byte there decoded
    as other pixels, silently (issue 61; zlib's own checksum ends the stream, past the last row Pillow
    reads). One line naming the file and the chunk; nothing for another format. A loop over chunks,
    not pixels (crc32: ~0.3 ms for a 640 x 480 16-bit depth image)."""
    fh.seek(0)
    if fh.read(8) != _PNG_MAGIC:
        fh.seek(0)
        return
    pos = 8
    while pos + 8 <= size:  # loop over chunks (tens to a few thousand)
        fh.seek(pos)
        head = fh.read(8)
        n, kind = int.from_bytes(head[:4], "big"), head[4:]
        if n > 2**31 - 1 or pos + 12 + n > size:
            raise ValueError(f"{where}: {what}: PNG chunk {kind!r} at byte {pos:,} says {n:,} bytes; the file "
                             f"has {size - pos - 12:,} after its header (truncated or damaged)")
        body = fh.read(n + 4)
        if zlib.crc32(body[:n], zlib.crc32(kind)) != int.from_bytes(body[n:], "big"):
            raise ValueError(f"{where}: {what}: PNG chunk {kind!r} at byte {pos:,} does not match its CRC (damaged)")
        if kind == b"IEND":
            break
        pos += 12 + n
    fh.seek(0)


def max_pixels() -> int | None:
    """The most pixels an image may declare: Pillow's ``Image.MAX_IMAGE_PIXELS`` (None: no cap)."""
    from PIL import Image

    return Image.MAX_IMAGE_PIXELS


# the bound on decoded bytes per byte of the file for each of Pillow's compressed decoders (module doc)
_RATIO = {"zip": 1032, "libtiff": 1400}
_CODEC = {"zip": "deflated (PNG)", "libtiff": "compressed TIFF"}


def _bits(rawmode: str, mode: str) -> int | None:
    """Bits per pixel of a Pillow raw mode ("I;16B": 16, "RGB": 24, "L;4": 4); None when unknown."""
    from PIL import ImageMode

    base, _, rest = str(rawmode).partition(";")
    try:
        info = ImageMode.getmode(base if base else mode)
    except KeyError:
        return None
    digits = "".join(c for c in rest if c.isdigit())
    if digits:
        return int(digits) * (len(info.bands) if int(digits) >= 8 else 1)
    return 1 if info.mode == "1" else len(info.bands) * np.dtype(info.typestr).itemsize * 8


def _check_declared(im, size: int, where: str, what: str) -> None:
    """The size ``im``'s header declares against the cap and the file's ``size`` bytes (module doc)."""
    w, h = im.size
    cap = max_pixels()
    if w <= 0 or h <= 0 or (cap is not None and w * h > cap):
        raise ValueError(f"{where}: {what} declares {w:,} x {h:,} pixels, expected at most {cap:,} "
                         f"(Image.MAX_IMAGE_PIXELS): a damaged or lying header")
    tiles = getattr(im, "tile", None) or []
    covered = sum(max(t[1][2] - t[1][0], 0) * max(t[1][3] - t[1][1], 0) for t in tiles)
    if tiles and covered < w * h:  # a TIFF whose strips stop short of its height: Pillow left the rest at 0
        raise ValueError(f"{where}: {what} declares {w:,} x {h:,} pixels ({im.format} {im.mode}); its data "
                         f"({len(tiles):,} strips or tiles) covers {covered:,} (a damaged or lying header)")
    for tile in tiles:  # loop over the file's tiles / strips (one to hundreds)
        codec, box, offset, args = tile[0], tile[1], int(tile[2] or 0), tile[3]
        tw, th = box[2] - box[0], box[3] - box[1]
        rawmode = args[0] if isinstance(args, tuple) else args
        bits = _bits(rawmode, im.mode) if isinstance(rawmode, str) else None
        left = size - offset
        if codec == "raw" and bits is not None and im.format in ("PPM", "TIFF"):
            need = math.ceil(tw * bits / 8) * th
            how = "raw pixel data"
        elif codec in _RATIO and bits is not None:
            need = math.ceil(math.ceil(tw * bits / 8) * th / _RATIO[codec])
            how = f"{_CODEC[codec]} data, at most {_RATIO[codec]:,}:1,"
        elif codec == "jpeg":
            need = math.ceil(math.ceil(tw / 8) * math.ceil(th / 8) / 64)
            how = "JPEG data, 1/8 bit per 8x8 block at least,"
        else:
            continue
        if need > left:
            raise ValueError(f"{where}: {what} declares {w:,} x {h:,} pixels ({im.format} {im.mode}): {how} needs "
                             f"{need:,} bytes, the file has {max(left, 0):,} (a damaged or lying header)")


@contextmanager
def open_image(source: Source, what: str, name: str | None = None, role: str | None = "frames"):
    """PIL image of ``source`` (a file, or an image's bytes named ``name``) whose pixels are loaded,
    its declared size checked before they are decoded (module doc); an unreadable, truncated,
    corrupt or lying file is one ValueError naming it (Pillow raises OSError, its decompression-bomb
    error and friends). A file is read once, its bytes hashed as the run's input of ``role``
    (:func:`diffuser_lab.data.inputs.record`; None: not an input)."""
    from PIL import Image, UnidentifiedImageError

    im, where = _opened(source, what, name, role)
    try:
        _check_deflate_strips(im, source, where, what)
    except ValueError:
        im.close()
        raise
    try:
        im.load()
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError, MemoryError, EOFError,
            Image.DecompressionBombError) as exc:
        im.close()
        raise ValueError(f"{where}: unreadable {what} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    with im:
        yield im


_DEFLATE = (8, 32946)  # TIFF's Compression tag: Adobe deflate, old-style deflate


def _check_deflate_strips(im, source: Source, where: str, what: str) -> None:
    """A deflated TIFF's strips decompressed whole before Pillow decodes them: libtiff stops inflating
    once a strip's rows are out, before zlib's Adler-32 at the stream's end, so a damaged byte decoded
    as other pixels, silently (issue 61). One line naming the file and the strip; nothing for another
    format or compression."""
    tags = getattr(im, "tag_v2", None)
    if im.format != "TIFF" or tags is None or tags.get(259) not in _DEFLATE:
        return
    offsets, counts = tags.get(273) or tags.get(324) or (), tags.get(279) or tags.get(325) or ()
    data = bytes(source) if isinstance(source, (bytes, bytearray, memoryview)) else Path(source).read_bytes()
    for k, (off, n) in enumerate(zip(offsets, counts)):  # loop over strips (one to hundreds)
        try:
            zlib.decompress(data[int(off):int(off) + int(n)])
        except zlib.error as exc:
            raise ValueError(f"{where}: {what}: deflated TIFF strip {k} at byte {int(off):,} is damaged ({exc})") from None


def image_size(source: Source, what: str, name: str | None = None) -> tuple[int, int]:
    """(H, W) an image's header declares, checked as :func:`open_image` checks it, no pixel decoded."""
    im, _ = _opened(source, what, name, None)
    with im:
        return int(im.size[1]), int(im.size[0])


_QUIET = threading.Lock()  # warnings.catch_warnings is process-wide: one reader's at a time


def _opened(source: Source, what: str, name: str | None, role: str | None):
    """(the lazily opened PIL image, the name errors give), its declared size checked; a file read
    whole and recorded as an input of ``role`` (None: its header only, not recorded)."""
    from PIL import Image, UnidentifiedImageError

    if isinstance(source, (bytes, bytearray, memoryview)):
        where, size = name or "<image bytes>", len(source)
        fh = io.BytesIO(bytes(source))
        _check_png_chunks(fh, size, where, what)
    else:
        path = Path(source)
        where = str(path)
        if not path.is_file():
            raise FileNotFoundError(f"{what} {path} does not exist")
        if role is None or not inputs.active():
            size = path.stat().st_size
            with open(path, "rb") as chunks:
                _check_png_chunks(chunks, size, where, what)
            fh = path  # Pillow opens (and closes) the file itself
        else:  # read once: the bytes decoded are the bytes hashed
            fh = io.BytesIO(inputs.read_bytes(path, role))
            size = len(fh.getbuffer())
            _check_png_chunks(fh, size, where, what)
    try:
        with _QUIET, warnings.catch_warnings():  # the size is refused below in one line, not warned of
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(fh)
    except Image.DecompressionBombError as exc:  # over twice the cap: Pillow's own sentence names no file
        n = re.search(r"\((\d+) pixels\)", str(exc))
        raise ValueError(f"{where}: {what} declares {int(n.group(1)) if n else 0:,} pixels, expected at most "
                         f"{max_pixels() or 0:,} (Image.MAX_IMAGE_PIXELS): a damaged or lying header") from None
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError, EOFError, MemoryError) as exc:
        raise ValueError(f"{where}: unreadable {what} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    try:
        _check_declared(im, size, where, what)
    except ValueError:
        im.close()
        raise
    return im, where


_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the empty IEND chunk, with its CRC: a PNG's last 12 bytes
_JPEG_END = b"\xff\xd9"  # EOI


def image_complete(path: str | Path) -> bool:
    """Whether an image file that a recorder may still be writing is whole: a PNG up to its IEND chunk,
    a JPEG up to its end marker (trailing zero bytes allowed), another format once it opens and decodes
    (:func:`open_image`). False for a missing file. Reads the file's last bytes (other formats: all)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
            fh.seek(0, 2)
            size = fh.tell()
            fh.seek(max(0, size - 64))
            tail = fh.read()
    except OSError:
        return False
    if head == _PNG_MAGIC:
        return tail.endswith(_PNG_END)
    if head[:2] == b"\xff\xd8":
        return tail.rstrip(b"\x00").endswith(_JPEG_END)
    try:
        with open_image(path, "image", role=None):
            return True
    except (ValueError, OSError):
        return False


def read_depth_png(path: str | Path, depth_scale: float, bit_shift: int = 0,
                   invalid=(0, 65535), shift_kind: str = "circular", role: str = "frames") -> np.ndarray:
    """16-bit depth PNG -> (H, W) float32 z-depth in metres, 0 = invalid.

    Args:
        depth_scale: stored units per metre (1000 for millimetres), applied after the shift.
        bit_shift: right shift of the raw 16-bit value before scaling.
        invalid: raw stored values (before the shift) meaning "no depth".
        shift_kind: ``circular`` = 16-bit rotate right (SUN3D, ``bit_shift=3``), ``plain`` =
            ``raw >> bit_shift`` (low bits dropped, e.g. ``(raw >> 3) / 1e4`` m).
        role: the run's input role of the file (:mod:`diffuser_lab.data.inputs`).
    """
    if shift_kind not in ("circular", "plain"):
        raise ValueError(f"depth shift kind {shift_kind!r}: expected circular or plain")
    path = Path(path)
    with open_image(path, "depth image", role=role) as im:
        raw = np.asarray(im)
    if raw.ndim != 2 or raw.dtype.kind not in "ui" or raw.dtype.itemsize < 2:
        raise ValueError(f"{path}: depth image of dtype {raw.dtype} shape {raw.shape}, expected single-channel 16-bit")
    if raw.dtype != np.uint16 or bit_shift:  # 16 bits of a wider type (a 16-bit PGM reads as int32), shifts
        raw = raw.astype(np.uint32) & 0xFFFF
    bad = None
    for v in invalid:  # the raw values meaning "no depth" (one or two): a comparison each
        if 0 <= int(v) <= 0xFFFF:
            bad = (raw == v) if bad is None else bad | (raw == v)
    if bit_shift and shift_kind == "plain":
        raw = raw >> int(bit_shift)
    elif bit_shift:
        s = int(bit_shift) % 16
        raw = ((raw >> s) | (raw << (16 - s))) & 0xFFFF  # 16-bit rotate right
    depth = np.divide(raw, np.float32(depth_scale), dtype=np.float32)
    if bad is not None:
        depth[bad] = 0.0
    return depth


def read_rgb(path: str | Path, shape: tuple[int, int] | None = None, role: str = "frames") -> np.ndarray:
    """Colour image -> (H, W, 3) uint8, resized to ``shape`` = (H, W) when given (:func:`resize_bilinear`)."""
    path = Path(path)
    with open_image(path, "colour image", role=role) as im:
        rgb = np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
    return rgb if shape is None else resize_bilinear(rgb, shape)


def read_label_png(path: str | Path, stored: bool = False, role: str = "frames") -> np.ndarray:
    """Single-channel label image -> (H, W) int64 ids (8/16-bit grey, 32-bit int, or palette indices);
    ``stored``: in the integer type the image holds them (uint8 / uint16 / int32: a mapping's lookup
    reads them as they are); ``role``: the run's input role of the file."""
    path = Path(path)
    with open_image(path, "label image", role=role) as im:
        if im.mode not in ("L", "P", "I", "I;16", "I;16B", "I;16L"):
            raise ValueError(f"{path}: label image mode {im.mode}, expected single-channel 8/16-bit ids "
                             f"(grey or palette), not colour-coded labels")
        arr = np.asarray(im)
    if stored:
        return arr if arr.dtype.kind in "iu" and arr.dtype.byteorder in "=|" else arr.astype(arr.dtype.newbyteorder("="))
    return arr.astype(np.int64)


def label_ids_in(files, n: int, what: str, role: str = "frames") -> list[tuple[np.ndarray, str]]:
    """The label ids in the first ``n`` of ``files`` (label images, in name order), as
    ``[(unique ids, "<k> <what> label images")]``; ``[]`` without files (``taxonomy=ids``)."""
    files = sorted(files)[:n]
    if not files:
        return []
    ids = np.unique(np.concatenate([np.unique(read_label_png(p, role=role)) for p in files]))  # <= n images
    return [(ids, f"{len(files)} {what} label images")]


def _npy_checked(fh, size: int, where: str) -> np.ndarray:
    """The array of an open ``.npy`` stream of ``size`` bytes, its header's shape x dtype checked
    against the bytes there before anything is allocated (a header that lies would ask for terabytes)."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise ValueError(f"format version {version}, expected 1.0, 2.0 or 3.0")
        start, width = fh.tell(), 2 if version == (1, 0) else 4
        hlen = int.from_bytes(fh.read(width), "little")
        if hlen > size - start - width:  # read before it is checked, a lying length allocates gigabytes
            raise ValueError(f"header length {hlen:,} beyond the file's {size:,} bytes")
        fh.seek(start)
        shape, fortran, dtype = (fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0)(fh)
    except (ValueError, OSError, EOFError, SyntaxError) as e:
        raise ValueError(f"{where}: not a .npy array ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
                         ) from None
    if dtype.hasobject:
        raise ValueError(f"{where}: array of Python objects ({dtype}), expected numbers")
    need = int(np.prod(shape, dtype=object)) * dtype.itemsize
    have = size - fh.tell()
    if need != have:
        raise ValueError(f"{where}: header says shape {shape} of {dtype} = {need:,} bytes, the file holds {have:,}")
    buf = fh.read(need)
    if len(buf) != need:
        raise ValueError(f"{where}: header says {need:,} bytes of {dtype}, the file ends after {len(buf):,}")
    return np.frombuffer(buf, dtype).reshape(shape, order="F" if fortran else "C")


def read_array(path: str | Path, what: str, key: str | None = None, role: str = "frames") -> np.ndarray:
    """A ``.npy`` file, or a ``.npz``'s array ``key`` (absent: its first), as stored, read only after its
    header's shape and dtype are checked against the file's bytes (one ValueError naming the file
    otherwise; missing file: FileNotFoundError). For depth and probability images kept as arrays;
    recorded as the run's input of ``role``."""
    import zipfile

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")
    inputs.record(path, role)
    if path.suffix.lower() == ".npz":
        try:
            with zipfile.ZipFile(path) as z:
                names = [n for n in z.namelist() if n.endswith(".npy")]
                if not names:
                    raise ValueError(f"{path}: empty .npz, expected a {what}")
                name = f"{key}.npy" if key is not None and f"{key}.npy" in names else names[0]
                info = z.getinfo(name)
                if info.file_size > 1100 * info.compress_size + 4096:  # deflate expands 1032:1 at most
                    raise ValueError(f"{path}: member {name} says {info.file_size:,} bytes from "
                                     f"{info.compress_size:,} compressed, more than deflate can expand to")
                with z.open(name) as fh:
                    return _npy_checked(fh, info.file_size, f"{path} [{name[:-4]}]")
        except (zipfile.BadZipFile, OSError, EOFError) as e:
            raise ValueError(f"{path}: unreadable .npz ({type(e).__name__}: {e})") from None
    with open(path, "rb") as fh:
        return _npy_checked(fh, path.stat().st_size, str(path))
