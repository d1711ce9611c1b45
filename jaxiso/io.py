"""Reading and writing volumes: numpy, raw bricks, NIfTI and VTK image data.

`load_volume` returns ``(array, meta)``. ``array[i, j, k]`` is the voxel at world
``origin + (i, j, k) * spacing`` (x = first index); `meta` holds ``format`` and, when the
file records them, ``spacing`` and ``origin`` (3-tuples of floats) and format-specific
extras (see `load_volume`). Arrays come back in native byte order.
"""

from __future__ import annotations

import base64
import lzma
import math
import os
import warnings
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np

__all__ = ["load_volume", "save_volume"]

_DATA_EXTRA = "pip install 'jaxiso[data]'"


def _format_of(path: Path) -> str:
    name = path.name.lower()
    for suffix, fmt in ((".nii.gz", "nifti"), (".nii", "nifti"), (".npy", "npy"),
                        (".npz", "npz"), (".vti", "vti")):
        if name.endswith(suffix):
            return fmt
    return "raw"  # .raw, .bin or anything else: a headerless brick


def _native(array: np.ndarray) -> np.ndarray:
    """The array in native byte order (jax rejects swapped ones)."""
    if array.dtype.byteorder not in "=|":
        return array.astype(array.dtype.newbyteorder("="))
    return array


def load_volume(path, *, shape=None, dtype=None, order: str = "C", offset: int = 0,
                array: str | None = None):
    """Read a volume; returns ``(array, meta)``.

    Formats, by file name:
      * ``.npy``; ``.npz`` (the key `array`, else ``data``, else its only array; ``spacing``
        and ``origin`` keys, as `save_volume` writes them, fill meta);
      * ``.nii`` / ``.nii.gz`` (needs nibabel): spacing from the header zooms, origin from the
        affine's translation, the full ``affine`` in meta and ``axis_aligned`` (False when the
        affine rotates or flips axes, which spacing and origin alone cannot represent). A 4-D
        image comes back 4-D with time last, ``meta["time_axis"] = 3`` and ``time_step``
        (a trailing time axis of length 1 is dropped);
      * ``.vti`` (VTK XML image data): read here for ascii, base64 and appended (raw or base64)
        arrays, uncompressed or zlib/lzma compressed; other variants go to pyvista when it is
        installed. `array` names the point-data array (default: the scalars, else the first).
        The pieces must cover WholeExtent and each must hold exactly the values its Extent
        needs (checked before anything is allocated);
      * anything else is a headerless raw brick: `shape` and `dtype` are required, `offset`
        bytes are skipped, `order` ("C": last index fastest, "F": first index fastest) gives
        the layout, and the file must hold exactly offset + prod(shape) * itemsize bytes.

    For self-describing formats a given `shape` or `dtype` is checked against the file.
    Errors: FileNotFoundError for a missing file; ValueError naming the file for a corrupt or
    inconsistent one; ImportError naming the ``jaxiso[data]`` extra when a reader is missing.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such volume file: {path}")
    fmt = _format_of(path)
    if array is not None and fmt not in ("npz", "vti"):
        raise ValueError(f"{path}: array= names an array in .npz or .vti files only")
    if fmt == "raw":
        data, meta = _load_raw(path, shape, dtype, order, offset)
    else:
        if fmt in ("npz", "vti"):
            data, meta = {"npz": _load_npz, "vti": _load_vti}[fmt](path, array)
        else:
            data, meta = {"npy": _load_npy, "nifti": _load_nifti}[fmt](path)
        _check_expected(path, data, shape, dtype)
    meta["format"] = fmt
    return _native(data), meta


def _check_expected(path, data, shape, dtype):
    if shape is not None and tuple(int(s) for s in shape) != data.shape:
        raise ValueError(f"{path}: holds shape {data.shape}, expected {tuple(shape)}")
    if dtype is not None and np.dtype(dtype) != data.dtype:
        raise ValueError(f"{path}: holds dtype {data.dtype}, expected {np.dtype(dtype)}")


def _load_raw(path, shape, dtype, order, offset):
    if shape is None or dtype is None:
        raise ValueError(f"{path}: a raw file (no known extension) needs shape= and dtype=; "
                         "known formats are .npy, .npz, .nii, .nii.gz, .vti")
    shape = tuple(int(s) for s in np.atleast_1d(shape))
    if any(s < 1 for s in shape):
        raise ValueError(f"shape must be positive, got {shape}")
    if order not in ("C", "F"):
        raise ValueError(f"order must be 'C' or 'F', got {order!r}")
    dtype = np.dtype(dtype)
    offset = int(offset)
    expected = offset + math.prod(shape) * dtype.itemsize
    actual = os.path.getsize(path)
    if actual != expected:
        raise ValueError(f"{path}: expected {expected} bytes (offset {offset} + {shape} x "
                         f"{dtype} of {dtype.itemsize} bytes), the file has {actual} bytes")
    flat = np.fromfile(path, dtype=dtype, offset=offset)
    return np.ascontiguousarray(flat.reshape(shape, order=order)), {}


def _load_npy(path):
    try:
        return np.load(path, allow_pickle=False), {}
    except (ValueError, OSError, EOFError) as err:
        raise ValueError(f"{path}: not a readable .npy file ({err})") from err


def _load_npz(path, name):
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (ValueError, OSError, EOFError) as err:
        raise ValueError(f"{path}: not a readable .npz file ({err})") from err
    meta = {k: tuple(float(v) for v in arrays.pop(k)) for k in ("spacing", "origin")
            if k in arrays and np.shape(arrays[k]) == (3,)}
    if name is not None:
        if name not in arrays:
            raise ValueError(f"{path}: no array {name!r}; it has {sorted(arrays)}")
        return arrays[name], meta
    if "data" in arrays:
        return arrays["data"], meta
    if len(arrays) == 1:
        return next(iter(arrays.values())), meta
    raise ValueError(f"{path}: has no 'data' array and several others {sorted(arrays)}; "
                     "save the volume under the key 'data'")


def _nibabel():
    try:
        import nibabel
    except ImportError as err:
        raise ImportError(f"reading/writing NIfTI needs nibabel: {_DATA_EXTRA}") from err
    return nibabel


def _load_nifti(path):
    nib = _nibabel()
    try:
        img = nib.load(str(path))
        data = np.asanyarray(img.dataobj)  # applies scl_slope/inter when the header has them
    except Exception as err:  # nibabel, gzip and zlib each raise their own kinds
        raise ValueError(f"{path}: not a readable NIfTI file ({err})") from err
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.ndim not in (3, 4):
        raise ValueError(f"{path}: NIfTI image of shape {data.shape} is not a 3-D volume "
                         "or a 4-D time series")
    affine = np.asarray(img.affine, np.float64)
    zooms = img.header.get_zooms()
    meta = {"spacing": tuple(float(z) for z in zooms[:3]),
            "origin": tuple(float(v) for v in affine[:3, 3]),
            "affine": affine,
            # spacing and origin describe the image fully only for a diagonal, positive affine
            "axis_aligned": bool(np.allclose(affine[:3, :3], np.diag(zooms[:3]), rtol=1e-6,
                                             atol=1e-6 * max(zooms[:3])))}
    if data.ndim == 4:
        meta["time_axis"] = 3
        if len(zooms) > 3:
            meta["time_step"] = float(zooms[3])
    return data, meta


# ---- VTK XML image data (.vti) ----------------------------------------------------------

class _Unsupported(Exception):
    """A valid .vti variant this reader does not handle (pyvista may)."""


_VTK_TYPES = {"Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4",
              "UInt32": "u4", "Int64": "i8", "UInt64": "u8", "Float32": "f4", "Float64": "f8"}


def _load_vti(path, name):
    raw = path.read_bytes()
    try:
        return _parse_vti(raw, name)
    except _Unsupported as err:
        try:
            import pyvista
        except ImportError:
            raise ValueError(f"{path}: {err}; install pyvista to read it") from None
        return _load_vti_pyvista(pyvista, path, name)
    except (ET.ParseError, ValueError, KeyError, IndexError, AttributeError, TypeError,
            zlib.error, lzma.LZMAError) as err:
        raise ValueError(f"{path}: not a readable .vti file ({type(err).__name__}: {err})") \
            from err


def _split_appended(raw: bytes) -> tuple[bytes, bytes]:
    """(xml without the appended payload, payload after the '_' marker). Raw appended bytes
    are not XML, so they are cut out before parsing."""
    start = raw.find(b"<AppendedData")
    if start < 0:
        return raw, b""
    mark = raw.index(b"_", raw.index(b">", start)) + 1
    end = raw.rfind(b"</AppendedData>")
    if end < mark:
        raise ValueError("unterminated AppendedData")
    return raw[:mark - 1] + raw[end:], raw[mark:end]


def _parse_vti(raw: bytes, name):
    xml, payload = _split_appended(raw)
    root = ET.fromstring(xml)
    if root.tag != "VTKFile" or root.get("type") != "ImageData":
        raise ValueError(f"not a VTK ImageData file (root {root.tag}, type {root.get('type')})")
    if root.get("byte_order", "LittleEndian") not in ("LittleEndian", "BigEndian"):
        raise ValueError(f"unknown byte_order {root.get('byte_order')}")
    endian = "<" if root.get("byte_order", "LittleEndian") == "LittleEndian" else ">"
    header_type = np.dtype(endian + _VTK_TYPES[root.get("header_type", "UInt32")])
    compressor = root.get("compressor")
    image = root.find("ImageData")
    whole = _extent(image.get("WholeExtent"), "WholeExtent")
    spacing = [float(v) for v in image.get("Spacing", "1 1 1").split()]
    origin = [float(v) for v in image.get("Origin", "0 0 0").split()]
    direction = image.get("Direction")
    if direction is not None and not np.allclose([float(v) for v in direction.split()],
                                                  np.eye(3).ravel()):
        raise _Unsupported("a rotated image (Direction is not the identity)")
    pieces = image.findall("Piece")
    if not pieces:
        raise ValueError("no Piece in ImageData")
    extents = [_extent(p.get("Extent"), f"Piece {i} Extent") for i, p in enumerate(pieces)]
    # Before decoding or allocating anything: the pieces must tile WholeExtent, so the
    # output is never larger than the values the file actually holds.
    _check_tiling(whole, extents)
    appended = root.find("AppendedData")
    codec = _Codec(header_type, compressor, endian)
    decoded = []
    for i, (piece, ext) in enumerate(zip(pieces, extents)):
        arr = _pick_array(piece.find("PointData"), name)
        values = codec.decode(arr, appended, payload, math.prod(_dims(ext)), f"Piece {i}")
        decoded.append((ext, values))
    out = np.zeros(_dims(whole), decoded[0][1].dtype)
    for ext, values in decoded:
        sl = tuple(slice(ext[2 * a] - whole[2 * a], ext[2 * a + 1] - whole[2 * a] + 1)
                   for a in range(3))
        out[sl] = values.reshape(_dims(ext), order="F")  # VTK runs x fastest
    # the grid's first node sits at Origin + WholeExtent start * Spacing
    first = tuple(o + whole[2 * a] * s for a, (o, s) in enumerate(zip(origin, spacing)))
    return out, {"spacing": tuple(spacing), "origin": first, "array": arr.get("Name")}


def _extent(text, what) -> list[int]:
    """Six ints x0 x1 y0 y1 z0 z1 (inclusive node ranges) with x0 <= x1 etc."""
    ext = [int(v) for v in (text or "").split()]
    if len(ext) != 6 or any(ext[2 * a] > ext[2 * a + 1] for a in range(3)):
        raise ValueError(f"{what} must be six ints 'x0 x1 y0 y1 z0 z1' with x0 <= x1 etc., "
                         f"got {text!r}")
    return ext


def _dims(ext) -> tuple[int, int, int]:
    return tuple(ext[2 * a + 1] - ext[2 * a] + 1 for a in range(3))


def _check_tiling(whole, extents):
    """Every piece lies inside WholeExtent and together they cover all of it; else a
    ValueError naming the offending piece or an uncovered extent. Pieces may overlap
    (parallel writers share boundary nodes). Works on the grid of piece boundaries, never on
    the voxels, so a huge declared extent costs nothing."""
    for i, ext in enumerate(extents):
        if any(ext[2 * a] < whole[2 * a] or ext[2 * a + 1] > whole[2 * a + 1]
               for a in range(3)):
            raise ValueError(f"Piece {i} Extent {_fmt(ext)} lies outside WholeExtent "
                             f"{_fmt(whole)}")
    # per axis, the sorted boundaries split the whole range into slabs [cuts[j], cuts[j+1])
    cuts = [np.unique([whole[2 * a], whole[2 * a + 1] + 1]
                      + [e[2 * a] for e in extents] + [e[2 * a + 1] + 1 for e in extents])
            for a in range(3)]
    covered = np.zeros([len(c) - 1 for c in cuts], bool)
    for ext in extents:
        covered[tuple(slice(np.searchsorted(c, ext[2 * a]),
                            np.searchsorted(c, ext[2 * a + 1] + 1))
                      for a, c in enumerate(cuts))] = True
    if not covered.all():
        cell = np.argwhere(~covered)[0]
        hole = [int(v) for a, j in enumerate(cell) for v in (cuts[a][j], cuts[a][j + 1] - 1)]
        raise ValueError(f"the pieces do not cover WholeExtent {_fmt(whole)}: nothing "
                         f"holds extent {_fmt(hole)} ({int((~covered).sum())} uncovered "
                         "block(s))")


def _fmt(ext) -> str:
    return "'" + " ".join(str(v) for v in ext) + "'"


def _pick_array(point_data, name):
    if point_data is None or not point_data.findall("DataArray"):
        raise ValueError("no point data arrays (cell data is not a volume of voxels)")
    arrays = point_data.findall("DataArray")
    names = [a.get("Name") for a in arrays]
    if name is None:
        name = point_data.get("Scalars") or names[0]
    if name not in names:
        raise ValueError(f"no point data array {name!r}; it has {names}")
    arr = arrays[names.index(name)]
    if int(arr.get("NumberOfComponents", "1")) != 1:
        raise ValueError(f"array {name!r} has {arr.get('NumberOfComponents')} components; "
                         "a volume needs a scalar array")
    return arr


class _Codec:
    """Decodes DataArray payloads: a header of `header_type` integers (byte count, or block
    table when compressed), then the bytes; base64 text may encode the header and the data
    together or separately (VTK and other writers differ)."""

    def __init__(self, header_type, compressor, endian):
        self.header_type = header_type
        self.endian = endian
        self.decompress = {None: None, "vtkZLibDataCompressor": zlib.decompress,
                           "vtkLZMADataCompressor": lzma.decompress}.get(compressor, "?")
        if self.decompress == "?":
            raise _Unsupported(f"compressor {compressor}")

    def decode(self, arr, appended, payload, count, where):
        dtype = np.dtype(self.endian + _VTK_TYPES[arr.get("type")])
        fmt = arr.get("format", "ascii")
        if fmt == "ascii":
            values = np.array((arr.text or "").split(), dtype=dtype)
        elif fmt == "binary":
            values = np.frombuffer(self._from_base64("".join(arr.text.split())), dtype)
        elif fmt == "appended":
            start = int(arr.get("offset"))
            if appended.get("encoding") == "raw":
                values = np.frombuffer(self._from_raw(payload, start), dtype)
            elif appended.get("encoding") == "base64":
                values = np.frombuffer(self._from_base64(payload[start:].decode("ascii")), dtype)
            else:
                raise _Unsupported(f"appended encoding {appended.get('encoding')}")
        else:
            raise ValueError(f"unknown DataArray format {fmt!r}")
        if values.size != count:  # too many is as corrupt as too few: never truncate
            raise ValueError(f"{where}: array {arr.get('Name')!r} holds {values.size} "
                             f"values, its Extent needs {count}")
        return values

    def _header_size(self, first: int) -> int:
        """Number of header integers given the first one (the block count if compressed)."""
        return 1 if self.decompress is None else 3 + first

    def _payload_size(self, header: np.ndarray) -> int:
        return int(header[0]) if self.decompress is None else int(header[3:].sum())

    def _blocks(self, header, data: bytes) -> bytes:
        if self.decompress is None:
            return data[:int(header[0])]
        out, pos = [], 0
        for size in header[3:].astype(np.int64):
            out.append(self.decompress(data[pos:pos + size]))
            pos += size
        return b"".join(out)

    def _from_raw(self, payload: bytes, start: int) -> bytes:
        item = self.header_type.itemsize
        first = int(np.frombuffer(payload[start:start + item], self.header_type)[0])
        nh = self._header_size(first) * item
        header = np.frombuffer(payload[start:start + nh], self.header_type)
        size = self._payload_size(header)
        data = payload[start + nh:start + nh + size]
        if len(data) < size:
            raise ValueError(f"appended data holds {len(data)} bytes, its header says {size}")
        return self._blocks(header, data)

    def _from_base64(self, text: str) -> bytes:
        item = self.header_type.itemsize
        chars = lambda nbytes: 4 * math.ceil(nbytes / 3)
        first = int(np.frombuffer(base64.b64decode(text[:chars(item)])[:item],
                                  self.header_type)[0])
        nh = self._header_size(first) * item
        header = np.frombuffer(base64.b64decode(text[:chars(nh)])[:nh], self.header_type)
        size = self._payload_size(header)
        # the header is encoded on its own (then padded) or together with the data; when nh
        # is a multiple of 3 both encodings are the same text
        if nh % 3 and text[chars(nh) - 1] == "=":
            data = base64.b64decode(text[chars(nh):chars(nh) + chars(size)])
        else:
            data = base64.b64decode(text[:chars(nh + size)])[nh:]
        if len(data) < size:
            raise ValueError(f"base64 data holds {len(data)} bytes, its header says {size}")
        return self._blocks(header, data)


def _load_vti_pyvista(pyvista, path, name):
    try:
        grid = pyvista.read(str(path))
        names = list(grid.point_data.keys())
        if not names:
            raise ValueError("no point data arrays")
        name = name if name is not None else names[0]
        values = np.asarray(grid.point_data[name])
        data = values.reshape(tuple(grid.dimensions), order="F")
    except Exception as err:
        raise ValueError(f"{path}: pyvista could not read it ({err})") from err
    return data, {"spacing": tuple(float(s) for s in grid.spacing),
                  "origin": tuple(float(o) for o in grid.origin), "array": name}


# ---- writing ----------------------------------------------------------------------------

def save_volume(path, array, *, spacing=None, origin=None) -> Path:
    """Write a volume so that `load_volume` reads it back; returns the path.

    ``.npy`` and raw (``.raw``, ``.bin``: C order, native byte order, no header) store only
    the voxels (a given spacing/origin is dropped with a warning: use ``.npz`` or NIfTI to
    keep them); ``.npz`` stores ``data``, ``spacing``, ``origin``; ``.nii``/``.nii.gz``
    (nibabel) store them in the affine diag(spacing) + origin. spacing defaults to
    (1, 1, 1) and origin to (0, 0, 0) where stored.
    """
    path = Path(path)
    name = path.name.lower()
    array = np.asarray(array)
    geometry = {k: tuple(float(x) for x in np.broadcast_to(np.asarray(v, np.float64), 3))
                for k, v in (("spacing", spacing), ("origin", origin)) if v is not None}
    if name.endswith((".npy", ".raw", ".bin")):
        if geometry:
            warnings.warn(f"{path.suffix} files store no {', '.join(geometry)}; it is dropped",
                          stacklevel=2)
        if name.endswith(".npy"):
            np.save(path, array)
        else:
            np.ascontiguousarray(array).tofile(path)
    elif name.endswith(".npz"):
        np.savez(path, data=array, spacing=geometry.get("spacing", (1.0, 1.0, 1.0)),
                 origin=geometry.get("origin", (0.0, 0.0, 0.0)))
    elif name.endswith((".nii", ".nii.gz")):
        nib = _nibabel()
        affine = np.diag(list(geometry.get("spacing", (1.0, 1.0, 1.0))) + [1.0])
        affine[:3, 3] = geometry.get("origin", (0.0, 0.0, 0.0))
        nib.save(nib.Nifti1Image(array, affine), str(path))
    else:
        raise ValueError(f"{path}: cannot write this format; use .npy, .npz, .raw, .bin, "
                         ".nii or .nii.gz")
    return path
