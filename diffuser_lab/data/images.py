"""Depth, colour and label images and ``.npy``/``.npz`` arrays shared by the capture formats and the
prediction files, each checked against what its header declares before it is decoded, and the one
resize of every image: :func:`resize_nearest` for label ids, depth and masks (values kept),
:func:`resize_bilinear` for colour and class probabilities (Pillow's bilinear)."""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import numpy as np

__all__ = ["read_depth_png", "read_rgb", "read_label_png", "label_ids_in", "read_array", "open_image", "resize_nearest",
           "resize_bilinear"]


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


def _check_png_chunks(path: Path, what: str) -> None:
    """A PNG's chunk lengths (big-endian uint32 before each chunk's type) against the file's size,
    before Pillow reads them: Pillow reads a chunk it skips at its declared length in one call, so a
    damaged length after the pixels asked for up to 4 GiB (MemoryError, no file named). One line
    naming the file and the chunk; nothing for another format. A loop over chunks, not pixels."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        if fh.read(8) != _PNG_MAGIC:
            return
        pos = 8
        while pos + 8 <= size:  # loop over chunks (tens to a few thousand)
            fh.seek(pos)
            head = fh.read(8)
            n, kind = int.from_bytes(head[:4], "big"), head[4:]
            if n > 2**31 - 1 or pos + 12 + n > size:
                raise ValueError(f"{path}: {what}: PNG chunk {kind!r} at byte {pos:,} says {n:,} bytes; the file "
                                 f"has {size - pos - 12:,} after its header (truncated or damaged)")
            if kind == b"IEND":
                return
            pos += 12 + n


@contextmanager
def open_image(path: str | Path, what: str):
    """PIL image of ``path`` whose pixels are loaded; an unreadable, truncated or corrupt file
    is one ValueError naming it (Pillow raises OSError and friends)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")
    _check_png_chunks(path, what)
    try:
        im = Image.open(path)
        im.load()
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable {what} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    with im:
        yield im




def read_depth_png(path: str | Path, depth_scale: float, bit_shift: int = 0,
                   invalid=(0, 65535), shift_kind: str = "circular") -> np.ndarray:
    """16-bit depth PNG -> (H, W) float32 z-depth in metres, 0 = invalid.

    Args:
        depth_scale: stored units per metre (1000 for millimetres), applied after the shift.
        bit_shift: right shift of the raw 16-bit value before scaling.
        invalid: raw stored values (before the shift) meaning "no depth".
        shift_kind: ``circular`` = 16-bit rotate right (SUN3D, ``bit_shift=3``), ``plain`` =
            ``raw >> bit_shift`` (low bits dropped, e.g. ``(raw >> 3) / 1e4`` m).
    """
    if shift_kind not in ("circular", "plain"):
        raise ValueError(f"depth shift kind {shift_kind!r}: expected circular or plain")
    path = Path(path)
    with open_image(path, "depth image") as im:
        raw = np.asarray(im)
    if raw.ndim != 2 or raw.dtype.kind not in "ui" or raw.dtype.itemsize < 2:
        raise ValueError(f"{path}: depth image of dtype {raw.dtype} shape {raw.shape}, expected single-channel 16-bit")
    raw = raw.astype(np.uint32) & 0xFFFF
    bad = np.isin(raw, np.asarray(invalid, np.uint32))
    if bit_shift and shift_kind == "plain":
        raw = raw >> int(bit_shift)
    elif bit_shift:
        s = int(bit_shift) % 16
        raw = ((raw >> s) | (raw << (16 - s))) & 0xFFFF  # 16-bit rotate right
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[bad] = 0.0
    return depth


def read_rgb(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Colour image -> (H, W, 3) uint8, resized to ``shape`` = (H, W) when given (:func:`resize_bilinear`)."""
    path = Path(path)
    with open_image(path, "colour image") as im:
        rgb = np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
    return rgb if shape is None else resize_bilinear(rgb, shape)


def read_label_png(path: str | Path) -> np.ndarray:
    """Single-channel label image -> (H, W) int64 ids (8/16-bit grey, 32-bit int, or palette indices)."""
    path = Path(path)
    with open_image(path, "label image") as im:
        if im.mode not in ("L", "P", "I", "I;16", "I;16B", "I;16L"):
            raise ValueError(f"{path}: label image mode {im.mode}, expected single-channel 8/16-bit ids "
                             f"(grey or palette), not colour-coded labels")
        arr = np.asarray(im)
    return arr.astype(np.int64)


def label_ids_in(files, n: int, what: str) -> list[tuple[np.ndarray, str]]:
    """The label ids in the first ``n`` of ``files`` (label images, in name order), as
    ``[(unique ids, "<k> <what> label images")]``; ``[]`` without files (``taxonomy=ids``)."""
    files = sorted(files)[:n]
    if not files:
        return []
    ids = np.unique(np.concatenate([np.unique(read_label_png(p)) for p in files]))  # <= n images
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


def read_array(path: str | Path, what: str, key: str | None = None) -> np.ndarray:
    """A ``.npy`` file, or a ``.npz``'s array ``key`` (absent: its first), as stored, read only after its
    header's shape and dtype are checked against the file's bytes (one ValueError naming the file
    otherwise; missing file: FileNotFoundError). For depth and probability images kept as arrays."""
    import zipfile

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")
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
