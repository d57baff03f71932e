"""A saved map on disk: a folder of two files, ``map.json`` (what the map is, and a table of its arrays) and
``map.bin`` (the arrays' raw little-endian bytes, each at an offset the table gives, with its CRC-32).

    write_map_folder(folder, header, arrays)     # map.bin, then map.json, each written whole or not at all
    header, arrays = read_map_folder(path)       # a map folder, its map.json, or a run folder holding map/

What the header and the arrays hold is ``ti_fusion.slam.saved_map``'s business (docs/MAPS.md); this module
knows the layout, the format version and what makes a folder unreadable: each problem is one
``InputError`` naming the file (missing, truncated, corrupted, of another format version, a run folder
without a saved map). Arrays are written as they are (no quantisation): 56 bytes per surfel
(scripts/bench_map_io.py).
"""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np

from ti_fusion.errors import InputError
from ti_fusion.io.outputs import atomic_path, atomic_write, is_run_folder

FORMAT = "ti-fusion map"
VERSION = 2  # raised with every change a reader of the previous version would misread (2: the trajectory)
READS = (1, 2)  # the versions this reader takes (a version 1 map has no trajectory: it loads without one)
HEADER = "map.json"
DATA = "map.bin"
RUN_SUBFOLDER = "map"  # where a run keeps its saved map
ALIGN = 64  # bytes: every array starts at a multiple of this in map.bin
# dtypes an array may have (little-endian), so a header cannot ask for an object array
DTYPES = ("<f4", "<f8", "<i4", "<i8", "|u1")


def write_map_folder(folder: str | Path, header: dict, arrays: dict[str, np.ndarray]) -> Path:
    """``folder`` (created if missing) holding ``map.bin`` (the arrays) and ``map.json`` (``header`` with the
    format, its version and the arrays' table added); map.json last, so that a folder whose writing was cut
    short has no header, or the previous one, whose checksums then refuse the new data."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    table, offset = {}, 0
    with atomic_path(folder / DATA) as tmp, open(tmp, "wb") as f:
        for name, array in arrays.items():
            a = np.ascontiguousarray(array)
            dtype = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
            if dtype.str not in DTYPES:
                raise TypeError(f"array {name}: dtype {a.dtype} is not one a map holds ({', '.join(DTYPES)})")
            a = a.astype(dtype, copy=False)
            pad = -offset % ALIGN
            f.write(b"\0" * pad)
            offset += pad
            data = memoryview(a).cast("B") if a.size else b""
            f.write(data)
            table[name] = {"dtype": dtype.str, "shape": list(a.shape), "offset": offset, "bytes": a.nbytes,
                           "crc32": zlib.crc32(data)}
            offset += a.nbytes
    full = {"format": FORMAT, "version": VERSION, **header, "arrays": table, "data_bytes": offset}
    with atomic_write(folder / HEADER, "w") as f:
        f.write(json.dumps(full, indent=1) + "\n")
    return folder


def find_map_folder(path: str | Path) -> Path | None:
    """The folder of the saved map that ``path`` names (a map folder, its map.json, or a run folder that holds
    one, ``map/``), or None: the one lookup ``map_folder``, ``ti-fusion mesh`` and ``inspect`` make."""
    path = Path(path)
    if path.is_file() and path.name == HEADER:
        return path.parent
    if path.is_dir():
        for folder in (path, path / RUN_SUBFOLDER):
            if (folder / HEADER).is_file():
                return folder
    return None


def map_folder(path: str | Path) -> Path:
    """The folder of the saved map that ``path`` names: a map folder, its map.json, or a run folder that holds
    one (``map/``); InputError otherwise."""
    path = Path(path)
    if (found := find_map_folder(path)) is not None:
        return found
    if not path.exists():
        raise InputError(path, "no such file or folder: expected a saved map (a folder with map.json) or a run "
                               "folder holding one")
    if not path.is_dir():
        raise InputError(path, f"not a saved map: expected a folder with {HEADER} (a run's {RUN_SUBFOLDER}/ "
                               f"folder) or the run folder itself")
    if is_run_folder(path):
        raise InputError(path, f"a ti-fusion run folder without a saved map (no {RUN_SUBFOLDER}/{HEADER}): only "
                               "slam runs save one, and an interrupted run or one from an older ti-fusion has none")
    raise InputError(path, f"holds no saved map: no {HEADER}, nor a run's {RUN_SUBFOLDER}/{HEADER}")


def read_header(path: str | Path) -> tuple[Path, dict]:
    """(the map folder, its header) of the saved map ``path`` names (``map_folder``), the format and version
    checked."""
    folder = map_folder(path)
    file = folder / HEADER
    try:
        header = json.loads(file.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InputError(file, "is damaged: not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise InputError(file, f"is damaged or truncated: not JSON ({exc.msg} at line {exc.lineno})") from None
    except OSError as exc:
        raise InputError(file, f"cannot be read: {exc.strerror or exc}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise InputError(file, f"is not a ti-fusion saved map (its format is not {FORMAT!r})")
    version = header.get("version")
    if version not in READS or isinstance(version, bool):
        raise InputError(file, f"is a saved map of format version {version!r}; this ti-fusion reads versions "
                               f"{' and '.join(map(str, READS))}" + (" (a newer ti-fusion wrote it)" if isinstance(
                                   version, int) and version > VERSION else ""))
    return folder, header


def _read_array(f, name: str, entry, size: int, folder: Path) -> np.ndarray:
    """Array ``name`` of the open map.bin ``f`` (``size`` bytes) as its table ``entry`` places it, read straight
    into an array of its own (the only copy a load makes) and its CRC-32 checked."""
    try:
        dtype, shape, offset, nbytes, crc = (entry["dtype"], tuple(int(s) for s in entry["shape"]),
                                             int(entry["offset"]), int(entry["bytes"]), int(entry["crc32"]))
    except (KeyError, TypeError, ValueError):
        raise InputError(folder / HEADER, f"is damaged: the entry of array {name!r}") from None
    if dtype not in DTYPES or offset < 0 or offset + nbytes > size or any(n < 0 for n in shape) or \
            nbytes != int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize:
        raise InputError(folder / HEADER, f"is damaged: array {name!r} does not fit {DATA}")
    array = np.empty(shape, dtype=dtype)
    raw = array.reshape(-1).view(np.uint8)  # its bytes (a memoryview cannot cast an empty array's)
    f.seek(offset)
    if f.readinto(raw) != nbytes:
        raise InputError(folder / DATA, "could not be read whole")
    if zlib.crc32(raw) != crc:
        raise InputError(folder / DATA, f"is corrupted: array {name!r} fails its checksum")
    return array


def read_map_folder(path: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """(header, name → array) of the saved map ``path`` names; every array's size and CRC-32 checked, so a
    truncated or corrupted map.bin is refused in one line naming it and the first bad array."""
    folder, header = read_header(path)
    file = folder / DATA
    table = header.get("arrays")
    expected = header.get("data_bytes")
    if not isinstance(table, dict) or not isinstance(expected, int):
        raise InputError(folder / HEADER, "is damaged: no table of arrays")
    if not file.is_file():
        raise InputError(file, f"is missing: the saved map's arrays ({expected} bytes) are not there")
    size = file.stat().st_size
    if size < expected:
        raise InputError(file, f"is truncated: {size} bytes of the {expected} that {HEADER} lists")
    if size > expected:
        raise InputError(file, f"has {size} bytes, more than the {expected} that {HEADER} lists: it belongs "
                               "to another save")
    arrays = {}
    try:
        with open(file, "rb") as f:
            for name, entry in table.items():
                arrays[name] = _read_array(f, name, entry, size, folder)
    except OSError as exc:
        raise InputError(file, f"cannot be read: {exc.strerror or exc}") from None
    return header, arrays
