"""Read and write Gaussians as a standard 3DGS ``.ply`` file.

The layout is the one written by the reference 3D Gaussian splatting code and
read by every common viewer (SuperSplat/PlayCanvas, antimatter15/splat, SPZ
tools, gsplat, nerfstudio):

* header ``ply`` / ``format binary_little_endian 1.0`` / ``element vertex N`` /
  one ``property float <name>`` line per property / ``end_header``, with ``\\n``
  line endings and no other element;
* one packed little-endian float32 record per Gaussian, properties in this order::

      x y z                              centre, world coordinates
      nx ny nz                           always zero (omitted with normals=False)
      f_dc_0 f_dc_1 f_dc_2               SH band-0 coefficient of R, G, B
      f_rest_0 .. f_rest_{3(K-1)-1}      higher SH bands, channel-major (see below)
      opacity                            opacity logit (alpha = sigmoid(opacity))
      scale_0 scale_1 scale_2            log standard deviations
      rot_0 rot_1 rot_2 rot_3            quaternion (w, x, y, z), not normalised

  With ``K = (d + 1)²`` coefficients per channel for SH degree ``d`` there are
  0, 9, 24 or 45 ``f_rest`` properties for degrees 0 to 3 (62 properties, 248
  bytes per Gaussian at degree 3).

``f_rest`` is channel-major: ``f_rest_0 .. f_rest_{K-2}`` are the R coefficients
1..K-1, then come the G coefficients, then the B ones. :class:`Gaussians` keeps
``sh`` band-major (``[N, K, 3]``), so ``f_rest = sh[:, 1:, :].transpose(1, 2)``
flattened per row.

Values are stored exactly as :class:`Gaussians` holds them (pre-activation), so a
write followed by a read is bit-exact for float32 Gaussians. Positions are in
the scene's world frame (OpenCV axes for macsplat scenes: x right, y down,
z forward of camera 0).

:func:`read_ply` also accepts files from other tools: any property order, with
or without normals, extra properties or elements (ignored), other numeric types
(cast to float32), ASCII and big-endian files, and any SH degree (degrees above
3 are truncated to 3 with a warning).
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import BinaryIO

import numpy as np
import plyfile
import torch

from ._atomic import atomic_path
from ._limits import check_regular_file
from .errors import OutputPathError, PlyFormatError
from .gaussians import Gaussians
from .sh import MAX_SH_DEGREE, num_sh_bases

__all__ = ["read_ply", "write_ply"]

logger = logging.getLogger(__name__)

_REQUIRED = (
    "x", "y", "z",
    "f_dc_0", "f_dc_1", "f_dc_2",
    "opacity",
    "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
)  # fmt: skip
_FLOAT_TYPES = (b"float", b"float32", b"f4")
_F_REST = re.compile(r"f_rest_(\d+)")
_HEADER_PROBE_BYTES = 1 << 16


# ---------------------------------------------------------------------------------------- writing
def _property_names(n_rest: int, normals: bool) -> list[str]:
    """Property names in the standard order for ``n_rest`` f_rest properties."""
    names = ["x", "y", "z"]
    if normals:
        names += ["nx", "ny", "nz"]
    names += ["f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(n_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(device="cpu", dtype=torch.float32).numpy()


def _write_records(f: BinaryIO, header: bytes, records: np.ndarray) -> None:
    """Write the header and the packed records (a C-contiguous ``'<f4'`` array) to ``f``."""
    f.write(header)
    f.write(records.data)
    f.flush()
    os.fsync(f.fileno())


def write_ply(path: str | os.PathLike[str], gaussians: Gaussians, *, normals: bool = True) -> int:
    """Write ``gaussians`` to ``path`` as a standard binary little-endian 3DGS PLY.

    The write is atomic: the file is written beside ``path`` under a temporary
    name and renamed onto it, so ``path`` is either untouched or complete.
    Gaussians with a NaN or Inf in any parameter are dropped (with a warning).

    Args:
        path: destination file; its folder must exist.
        gaussians: the Gaussians, any floating dtype and device (cast to float32,
            detached, moved to the CPU). SH degree 0–3.
        normals: write the all-zero ``nx ny nz`` properties, as the reference
            implementation does. Some exporters (gsplat) omit them.

    Returns:
        The number of Gaussians written.

    Raises:
        OutputPathError: the file cannot be written (missing folders are created).
    """
    n = len(gaussians)
    k = gaussians.sh.shape[1]
    names = _property_names(3 * (k - 1), normals)
    records = np.empty((n, len(names)), dtype="<f4")
    col = 0

    def put(values: np.ndarray) -> None:
        nonlocal col
        width = values.shape[1]
        records[:, col : col + width] = values
        col += width

    put(_to_numpy(gaussians.means))
    if normals:
        put(np.zeros((n, 3), dtype=np.float32))
    sh = _to_numpy(gaussians.sh)
    put(sh[:, 0, :])
    put(sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)))
    put(_to_numpy(gaussians.opacity_logits)[:, None])
    put(_to_numpy(gaussians.log_scales))
    put(_to_numpy(gaussians.quats))
    assert col == len(names), (col, len(names))

    finite = np.isfinite(records).all(axis=1)
    dropped = n - int(finite.sum())
    if dropped:
        logger.warning("%s: dropped %d of %d Gaussians with NaN or Inf parameters", path, dropped, n)
        records = records[finite]
    count = records.shape[0]

    header = "".join(
        ["ply\n", "format binary_little_endian 1.0\n", f"element vertex {count}\n"]
        + [f"property float {name}\n" for name in names]
        + ["end_header\n"]
    ).encode("ascii")
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            _write_records(f, header, np.ascontiguousarray(records))
    except OSError as e:
        raise OutputPathError(f"cannot write {path}: {e.strerror or e}") from e
    logger.debug("%s: wrote %d Gaussians (SH degree %d)", path, count, gaussians.sh_degree)
    return count


# ---------------------------------------------------------------------------------------- reading
class _Columns:
    """Numeric columns of the ``vertex`` element, by property name."""

    def __init__(self, names: Sequence[str], count: int) -> None:
        self.names = list(names)
        self.count = count

    def take(self, names: Sequence[str]) -> np.ndarray:
        """The named columns as one float32 array. [count, len(names)]"""
        raise NotImplementedError


class _PackedColumns(_Columns):
    """Columns of a packed float32 record array (the standard layout, read with numpy)."""

    def __init__(self, names: Sequence[str], data: np.ndarray) -> None:
        super().__init__(names, data.shape[0])
        self.data = data
        self.index = {name: i for i, name in enumerate(names)}

    def take(self, names: Sequence[str]) -> np.ndarray:
        # Copy runs of consecutive columns as slices: far faster than fancy indexing,
        # and the standard layout is a few long runs.
        idx = [self.index[name] for name in names]
        out = np.empty((self.count, len(idx)), dtype=np.float32)
        start = 0
        while start < len(idx):
            stop = start + 1
            while stop < len(idx) and idx[stop] == idx[stop - 1] + 1:
                stop += 1
            out[:, start:stop] = self.data[:, idx[start] : idx[start] + stop - start]
            start = stop
        return out


class _StructuredColumns(_Columns):
    """Columns of a plyfile element (any type, byte order, or format)."""

    def __init__(self, element: plyfile.PlyElement) -> None:
        # List properties cannot hold a per-Gaussian scalar; leave them out.
        scalars = [p.name for p in element.properties if not isinstance(p, plyfile.PlyListProperty)]
        super().__init__(scalars, len(element.data))
        self.element = element

    def take(self, names: Sequence[str]) -> np.ndarray:
        out = np.empty((self.count, len(names)), dtype=np.float32)
        for i, name in enumerate(names):
            out[:, i] = self.element.data[name]
        return out


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


def _read_fast(path: Path, size: int, head: bytes) -> _PackedColumns | None:
    """Read the exact standard layout with numpy; ``None`` if the file is anything else.

    Accepted: binary little-endian, a single ``vertex`` element whose properties are
    all scalar float32, and a file size that matches the header exactly. Everything
    else goes through plyfile.
    """
    header = _header_lines(head)
    if header is None or b"\r" in head[: header[1]]:
        return None
    lines, header_len = header
    if lines[:2] != [b"ply", b"format binary_little_endian 1.0"]:
        return None
    count: int | None = None
    names: list[str] = []
    for line in lines[2:]:
        words = line.split()
        if not words or words[0] in (b"comment", b"obj_info"):
            continue
        if words[0] == b"element":
            if count is not None or len(words) != 3 or words[1] != b"vertex" or not words[2].isdigit():
                return None
            count = int(words[2])
        elif words[0] == b"property" and count is not None and len(words) == 3 and words[1] in _FLOAT_TYPES:
            try:
                names.append(words[2].decode("ascii"))
            except UnicodeDecodeError:
                return None
        else:
            return None
    if count is None or not names or len(set(names)) != len(names):
        return None
    n_values = count * len(names)
    if size != header_len + 4 * n_values:
        return None
    data = np.fromfile(path, dtype="<f4", count=n_values, offset=header_len)
    if data.size != n_values:
        return None
    return _PackedColumns(names, data.reshape(count, len(names)))


def _read_plyfile(path: Path) -> _StructuredColumns:
    """Read any PLY with plyfile; return the ``vertex`` element's columns."""
    try:
        # Reading from a path lets plyfile memory-map binary elements; reading from an
        # open stream without mmap is orders of magnitude slower for large files.
        ply = plyfile.PlyData.read(str(path))
    except (plyfile.PlyParseError, ValueError, EOFError) as e:  # UnicodeDecodeError is a ValueError
        raise PlyFormatError(f"{path}: not a valid PLY file ({_one_line(e)})") from e
    except OSError as e:
        raise PlyFormatError(f"{path}: cannot read ({e.strerror or e})") from e
    try:
        vertex = ply["vertex"]
    except KeyError:
        elements = ", ".join(el.name for el in ply.elements) or "none"
        raise PlyFormatError(f"{path}: no 'vertex' element (elements: {elements})") from None
    return _StructuredColumns(vertex)


# Bytes per value of each PLY scalar type (all the names plyfile accepts).
_PLY_TYPE_BYTES = {
    **dict.fromkeys(("char", "int8", "i1", "uchar", "uint8", "u1"), 1),
    **dict.fromkeys(("short", "int16", "i2", "ushort", "uint16", "u2"), 2),
    **dict.fromkeys(("int", "int32", "i4", "uint", "uint32", "u4", "float", "float32", "f4"), 4),
    **dict.fromkeys(("double", "float64", "f8"), 8),
}


def _header_lines(head: bytes) -> tuple[list[bytes], int] | None:
    """The header's lines before the ``end_header`` line, and the header's length in bytes; None without one.

    The PLY grammar is line by line: ``end_header`` ends the header only as a line of its own (a ``comment``
    line that mentions it is a comment), and the body starts after that line's ``\\n``. The lines keep a
    ``\\r`` of CRLF files.
    """
    lines: list[bytes] = []
    start = 0
    while (nl := head.find(b"\n", start)) >= 0:
        line = head[start:nl]
        if line.strip() == b"end_header":
            return lines, nl + 1
        lines.append(line)
        start = nl + 1
    return (lines, len(head)) if head[start:].strip() == b"end_header" else None


def _check_declared_sizes(path: Path, size: int, head: bytes) -> None:
    """Refuse a header whose element counts need more bytes than the file has, before anything is allocated.

    Binary records need at least the sum of their scalar sizes (a list property at least its length
    field); ASCII records at least two bytes (a digit and a separator) per value. Headers this check
    does not understand are left to plyfile, which reports them.

    Raises:
        PlyFormatError: the header declares more data than the file holds, or has no ``end_header``
            within its first 64 KiB.
    """
    header = _header_lines(head)
    if header is None:
        if size > len(head):
            raise PlyFormatError(f"{path}: no 'end_header' line within the first {_HEADER_PROBE_BYTES // 1024} KiB")
        return  # plyfile reports the missing end_header
    lines, header_len = header
    fmt = ""
    elements: list[list] = []  # [name, count, bytes per binary record, values per record]
    for raw in lines:
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append([words[1], int(words[2]), 0, 0])
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
            if words[2] not in _PLY_TYPE_BYTES:
                return
            elements[-1][2] += _PLY_TYPE_BYTES[words[2]]
            elements[-1][3] += 1
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPE_BYTES:
            elements[-1][2] += _PLY_TYPE_BYTES[words[1]]
            elements[-1][3] += 1
        elif words[0] not in ("ply", "format"):
            return  # malformed: plyfile says how
    if fmt == "ascii":
        need = sum(count * max(1, 2 * n_values) for _, count, _, n_values in elements) - 1
    elif fmt.startswith("binary"):
        need = sum(count * max(1, n_bytes) for _, count, n_bytes, _ in elements)
    else:
        return
    available = size - header_len
    if need > available:
        declared = ", ".join(f"{count} '{name}'" for name, count, _, _ in elements)
        raise PlyFormatError(
            f"{path}: the header declares {declared} elements, which need at least {need} bytes of {fmt} data, "
            f"but only {max(available, 0)} bytes follow the header (truncated or corrupt file)"
        )


def _open_columns(path: Path) -> _Columns:
    """Open ``path`` and return the ``vertex`` columns (fast path first, then plyfile)."""
    size = check_regular_file(path, PlyFormatError, "a PLY file")
    try:
        with open(path, "rb") as f:
            head = f.read(_HEADER_PROBE_BYTES)
    except OSError as e:
        raise PlyFormatError(f"{path}: cannot read ({e.strerror or e})") from e
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        raise PlyFormatError(f"{path}: not a PLY file (it does not start with 'ply')")
    _check_declared_sizes(path, size, head)
    try:
        fast = _read_fast(path, size, head)
    except OSError as e:
        raise PlyFormatError(f"{path}: cannot read ({e.strerror or e})") from e
    return fast if fast is not None else _read_plyfile(path)


def _sh_layout(path: Path, names: Sequence[str]) -> tuple[int, list[str]]:
    """SH degree to load and the f_rest names to read, in channel-major file order."""
    rest = sorted(int(m.group(1)) for name in names if (m := _F_REST.fullmatch(name)))
    n_rest = len(rest)
    if rest != list(range(n_rest)):
        raise PlyFormatError(f"{path}: f_rest properties are not numbered 0..{n_rest - 1}")
    degree = 0
    while 3 * (num_sh_bases(degree) - 1) < n_rest:
        degree += 1
    if 3 * (num_sh_bases(degree) - 1) != n_rest:
        raise PlyFormatError(
            f"{path}: {n_rest} f_rest properties is not 3·((d+1)²−1) for any SH degree d (expected 0, 9, 24 or 45)"
        )
    per_channel_file = num_sh_bases(degree) - 1
    if degree > MAX_SH_DEGREE:
        logger.warning("%s: SH degree %d truncated to degree %d (higher bands dropped)", path, degree, MAX_SH_DEGREE)
        degree = MAX_SH_DEGREE
    per_channel = num_sh_bases(degree) - 1
    wanted = [f"f_rest_{c * per_channel_file + j}" for c in range(3) for j in range(per_channel)]
    return degree, wanted


def read_ply(path: str | os.PathLike[str]) -> Gaussians:
    """Read Gaussians from a 3DGS PLY file.

    Reads the standard layout written by :func:`write_ply` and by other 3DGS tools.
    Required properties of element ``vertex``: ``x y z f_dc_0..2 opacity scale_0..2
    rot_0..3``; ``f_rest_*`` is optional (0, 9, 24, 45 properties for SH degree
    0–3; more is truncated to degree 3 with a warning). Normals, other properties
    and other elements are ignored; any numeric type is cast to float32. Rows with
    a NaN or Inf are dropped (with a warning).

    Args:
        path: the PLY file (binary little- or big-endian, or ASCII).

    Returns:
        Float32 CPU Gaussians holding the file's values unchanged.

    Raises:
        PlyFormatError: the file is missing, unreadable, not a PLY, truncated, or
            lacks a required property.
    """
    p = Path(path)
    columns = _open_columns(p)
    missing = [name for name in _REQUIRED if name not in columns.names]
    if missing:
        raise PlyFormatError(f"{p}: missing 3DGS properties {', '.join(missing)} in element 'vertex'")
    degree, rest_names = _sh_layout(p, columns.names)
    block = columns.take(list(_REQUIRED[:6]) + rest_names + list(_REQUIRED[6:]))
    n = block.shape[0]
    finite = np.isfinite(block).all(axis=1)
    dropped = n - int(finite.sum())
    if dropped:
        logger.warning("%s: dropped %d of %d Gaussians with NaN or Inf parameters", p, dropped, n)
        block = block[finite]
        n = block.shape[0]

    r = len(rest_names)
    k = num_sh_bases(degree)
    sh = np.empty((n, k, 3), dtype=np.float32)
    sh[:, 0, :] = block[:, 3:6]
    sh[:, 1:, :] = block[:, 6 : 6 + r].reshape(n, 3, k - 1).transpose(0, 2, 1)
    tail = block[:, 6 + r :]
    return Gaussians(
        means=torch.from_numpy(np.ascontiguousarray(block[:, 0:3])),
        log_scales=torch.from_numpy(np.ascontiguousarray(tail[:, 1:4])),
        quats=torch.from_numpy(np.ascontiguousarray(tail[:, 4:8])),
        opacity_logits=torch.from_numpy(np.ascontiguousarray(tail[:, 0])),
        sh=torch.from_numpy(sh),
    )
