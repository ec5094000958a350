"""Versioned, pickle-free artefact files, written atomically.

Array files are ``.npz`` archives read with ``allow_pickle=False``; next to the arrays they
carry a JSON header (``__meta__``) with the format name, schema version, package version,
the configuration that produced them and a SHA-256 digest of the arrays. Loading checks all
of these. JSON files are written the same way (temporary file, fsync, rename), so an
interrupted run leaves either the old file or the new one, never a torn one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import io
import json
import math
import os
import shutil
import uuid
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from rrtcolearn import __version__
from rrtcolearn.data.dataset import Dataset
from rrtcolearn.errors import ArtefactError

SCHEMA_VERSION = 1
_META = "__meta__"


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same directory and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory, give a file name", str(path))
    tmp = path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    try:
        # os.open with 0o666 honours the umask, unlike mkstemp's fixed 0o600
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except OSError as exc:  # the user's path, not the temporary file's, in the message
        raise type(exc)(exc.errno, f"{exc.strerror} (writing into {path.parent})",
                        str(path)) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise type(exc)(exc.errno, exc.strerror, str(path)) from None
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=1, allow_nan=False) + "\n")


def read_json(path: str | os.PathLike, what: str = "file") -> Any:
    path = Path(path)
    if not path.is_file():
        raise ArtefactError(f"{what} not found: {path}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    # ValueError: JSONDecodeError, UnicodeDecodeError and an integer too long to convert;
    # RecursionError: brackets nested deeper than the parser's stack
    except (ValueError, RecursionError) as exc:
        raise ArtefactError(f"{what} {path} is not valid JSON ({_one_line(exc)})") from None


def json_checksum(content: dict) -> str:
    """SHA-256 of a JSON document's canonical form, without its own ``sha256`` field."""
    body = {k: v for k, v in content.items() if k != "sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":"))
                          .encode()).hexdigest()


def write_checked_json(path: str | Path, content: dict) -> None:
    """Write a JSON artefact with its checksum, atomically."""
    write_json(path, {**content, "sha256": json_checksum(content)})


def read_checked_json(path: str | Path, fmt: str, schema: int, what: str) -> dict:
    """Read a JSON artefact, refusing another format, schema or a failed checksum."""
    info = read_json(path, what)
    if not isinstance(info, dict) or info.get("format") != fmt:
        raise ArtefactError(f"{path} is not an rrtcolearn {what}")
    if info.get("schema_version") != schema:
        raise ArtefactError(f"{path} has schema version {info.get('schema_version')}, "
                            f"expected {schema}")
    if info.get("sha256") != json_checksum(info):
        raise ArtefactError(f"{path} fails its checksum: the file was modified or damaged")
    return info


def digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over arrays in name order: name, dtype, shape and C-order bytes."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(a.dtype.str.encode())
        h.update(repr(a.shape).encode())
        # the array's own buffer, not a `tobytes` copy: the same bytes without a transient
        # copy of each array (a model's largest is ~100 MB)
        h.update(memoryview(a.reshape(-1)).cast("B") if a.size else b"")
    return h.hexdigest()


def save_arrays(path: str | os.PathLike, fmt: str, arrays: dict[str, np.ndarray],
                meta: dict[str, Any]) -> str:
    """Write arrays and a checked header to ``path`` atomically; returns the arrays' digest."""
    for name, a in arrays.items():
        if a.dtype == object:
            raise TypeError(f"array {name!r} has dtype object, which cannot be stored safely")
    header = {
        **meta,
        "format": fmt,
        "schema_version": SCHEMA_VERSION,
        "package_version": __version__,
        "sha256": digest(arrays),
    }
    buf = io.BytesIO()
    np.savez(buf, **arrays, **{_META: np.array(json.dumps(header, allow_nan=False))})
    atomic_write_bytes(path, buf.getvalue())
    return header["sha256"]


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line (a parser's may quote the damaged bytes)."""
    return " ".join(str(exc).split())


# members at least this large are read straight from the file (`_read_stored`)
_DIRECT_BYTES = 1 << 20


def _read_stored(npz, fh, name: str) -> np.ndarray:
    """The array ``name`` of an open `np.load` archive. A large member stored uncompressed
    (as `save_arrays` writes them) is read from the file ``fh`` into its array in one
    read, after zipfile's checks of the member (its local header, flags and compression)
    and numpy's of the .npy header. np.load copies it in 256 KiB pieces through zipfile,
    which also computes its CRC: 0.18-0.30 s CPU against 0.11-0.17 s for the 106-169 MB
    file of a 4-state model (docs/performance.md); its bytes are checked by the arrays'
    SHA-256 digest instead, in `load_arrays`. Anything else, e.g. an object dtype that
    np.load refuses, goes through np.load."""
    try:
        info = npz.zip.getinfo(f"{name}.npy")
    except KeyError:  # a member np.load names otherwise
        return npz[name]
    if info.compress_type != zipfile.ZIP_STORED or info.file_size < _DIRECT_BYTES:
        return npz[name]
    with npz.zip.open(info) as member:
        version = np.lib.format.read_magic(member)
        if version not in ((1, 0), (2, 0)):
            return npz[name]
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, fortran, dtype = read_header(member)
        offset = member.tell()
    count = math.prod(shape)
    if dtype.hasobject or offset + count * dtype.itemsize != info.file_size:
        return npz[name]  # np.load's refusal, or its error for a member of another size
    fh.seek(info.header_offset)
    local = fh.read(30)  # the local header, which zipfile has just checked
    fh.seek(info.header_offset + 30 + int.from_bytes(local[26:28], "little")
            + int.from_bytes(local[28:30], "little") + offset)
    flat = np.fromfile(fh, dtype=dtype, count=count)
    if flat.size != count:
        raise ValueError(f"{name}.npy: the file ends inside the array")
    return flat.reshape(shape[::-1]).T if fortran else flat.reshape(shape)


def load_arrays(path: str | os.PathLike, fmt: str) -> tuple[dict[str, np.ndarray], dict]:
    """Read a file written by `save_arrays`, refusing anything that does not check out."""
    path = Path(path)
    if not path.is_file():
        raise ArtefactError(f"{fmt} file not found: {path}")
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head != b"PK\x03\x04":  # np.load would take anything else for a pickle
        raise ArtefactError(f"{path} is not a readable {fmt} file (not a zip archive: "
                            "truncated, corrupt or another kind of file)")
    try:
        # one open file for both readers (zipfile seeks to its own position on each
        # read): the members read directly are those of the archive np.load read
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as npz:
            arrays = {k: _read_stored(npz, fh, k) for k in npz.files}
    # Damaged bytes reach several parsers, each with its own exceptions: zipfile (BadZipFile;
    # RuntimeError for a flag bit that says "encrypted"; NotImplementedError for a zip version
    # or compression method it lacks), the decompressors (zlib.error, EOFError, OSError) and
    # numpy's .npy header parser (tokenize.TokenError, SyntaxError, ValueError, KeyError).
    # Naming them missed some (issue 34); whichever it is, the file cannot be read.
    except Exception as exc:
        if isinstance(exc, ValueError) and "allow_pickle" in str(exc):  # numpy's own refusal
            raise ArtefactError(f"{path} holds data that would need unpickling, refused "
                                f"({_one_line(exc)})") from None
        raise ArtefactError(f"{path} is not a readable {fmt} file (truncated or corrupt: "
                            f"{type(exc).__name__}: {_one_line(exc)})") from None
    if _META not in arrays:
        raise ArtefactError(f"{path} has no header: not an rrtcolearn {fmt} file")
    try:
        meta = json.loads(str(arrays.pop(_META)))
    except json.JSONDecodeError:
        raise ArtefactError(f"{path} has a corrupt header") from None
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise ArtefactError(f"{path} is a {found!r} file, expected {fmt!r}")
    if meta.get("schema_version") != SCHEMA_VERSION:
        raise ArtefactError(f"{path} has schema version {meta.get('schema_version')}, this "
                            f"rrtcolearn reads version {SCHEMA_VERSION}")
    if digest(arrays) != meta.get("sha256"):
        raise ArtefactError(f"{path} fails its checksum: the arrays were modified or damaged")
    return arrays, meta


DATASET_FORMAT = "rrtcolearn.dataset"


def save_dataset(path: str | os.PathLike, data: Dataset, meta: dict[str, Any]) -> str:
    """Store a dataset compactly: per-simulation starts and costates, per-point ends and costs."""
    sims, inverse = np.unique(data.simulation, return_inverse=True)
    first = np.zeros(len(sims), dtype=np.int64)
    first[inverse[::-1]] = np.arange(len(data))[::-1]
    arrays = {
        "sim_id": sims.astype(np.int64),
        "sim_x0": data.x0[first],
        "sim_params": data.params[first],
        "sim_costate": data.costate[first],
        "point_sim": inverse.astype(np.int32),
        "point_x1": data.x1,
        "point_cost": data.cost,
        "point_duration": data.duration,
    }
    return save_arrays(path, DATASET_FORMAT, arrays, meta)


def load_dataset(path: str | os.PathLike, system: str | None = None) -> tuple[Dataset, dict]:
    """Read a dataset file; ``system`` (if given) must match the one it was generated for."""
    arrays, meta = load_arrays(path, DATASET_FORMAT)
    if system is not None and meta.get("system") != system:
        raise ArtefactError(f"{path} holds data of system {meta.get('system')!r}, "
                            f"not {system!r}")
    try:
        s = arrays["point_sim"]
        if s.size and (s.min() < 0 or s.max() >= len(arrays["sim_id"])):
            raise ArtefactError(f"{path} has point rows that refer to missing simulations")
        data = Dataset.from_arrays({
            "x0": arrays["sim_x0"][s],
            "x1": arrays["point_x1"],
            "cost": arrays["point_cost"],
            "params": arrays["sim_params"][s],
            "duration": arrays["point_duration"],
            "costate": arrays["sim_costate"][s],
            "simulation": arrays["sim_id"][s],
        })
    except (KeyError, IndexError, ValueError) as exc:
        raise ArtefactError(f"{path} is not a consistent dataset ({exc})") from None
    return data, meta


SHARD_MANIFEST = "manifest.json"


class ShardStore:
    """Finished chunks of a long computation, one atomically written file each.

    The manifest names the computation (``key``) and its number of chunks; shards of another
    computation found in the directory are discarded, and a shard that fails to load is
    recomputed, so nothing half-written or foreign is ever used.
    """

    def __init__(self, directory: str | os.PathLike, key: str, n_chunks: int):
        self.directory = Path(directory)
        manifest = {"format": "rrtcolearn.shards", "schema_version": SCHEMA_VERSION,
                    "key": key, "n_chunks": n_chunks}
        path = self.directory / SHARD_MANIFEST
        current = None
        if path.is_file():
            with contextlib.suppress(ArtefactError):
                current = read_json(path)
        if current != manifest:
            self.remove()
            write_json(path, manifest)

    def _path(self, chunk: int) -> Path:
        return self.directory / f"chunk-{chunk:06d}.npz"

    def load(self, chunk: int, system: str):
        """(Dataset, GenerationStats-like dict) of a finished chunk, or None."""
        path = self._path(chunk)
        if not path.is_file():
            return None
        try:
            data, meta = load_dataset(path, system)
        except ArtefactError:
            return None
        from rrtcolearn.data.generate import GenerationStats

        return data, GenerationStats(**meta["stats"])

    def save(self, chunk: int, result, meta: dict) -> None:
        data, stats = result
        if not isinstance(data, Dataset):
            data = data.expand()
        save_dataset(self._path(chunk), data, {**meta, "chunk": chunk,
                                               "stats": dataclasses.asdict(stats)})

    def remove(self) -> None:
        if self.directory.is_dir():
            shutil.rmtree(self.directory)
        with contextlib.suppress(OSError):  # the parent too, once no other store uses it
            self.directory.parent.rmdir()
