"""Artefact files: round trip, and refusal of anything truncated, tampered or pickled."""

import io
import json
import os
import zipfile

import numpy as np
import pytest

from rrtcolearn.data.store import (
    atomic_write_bytes,
    digest,
    load_arrays,
    load_dataset,
    save_arrays,
    save_dataset,
)
from rrtcolearn.errors import ArtefactError


def test_dataset_round_trip(small_dataset, tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(path, small_dataset, {"system": "pendulum"})
    back, meta = load_dataset(path, "pendulum")
    for k, v in small_dataset.arrays().items():
        assert np.array_equal(v, back.arrays()[k]), k
    assert meta["format"] == "rrtcolearn.dataset" and meta["schema_version"] == 1
    with pytest.raises(ArtefactError, match="system"):
        load_dataset(path, "cartpole")


def test_truncated_file_is_refused(small_dataset, tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(path, small_dataset, {"system": "pendulum"})
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ArtefactError):
        load_dataset(path)


def test_tampered_array_fails_the_checksum(tmp_path):
    path = tmp_path / "a.npz"
    save_arrays(path, "rrtcolearn.test", {"a": np.arange(5.0)}, {})
    with zipfile.ZipFile(path) as z:
        meta = z.read("__meta__.npy")
    buf = io.BytesIO()
    np.savez(buf, a=np.arange(5.0) + 1)
    with zipfile.ZipFile(buf) as z:
        a = z.read("a.npy")
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("a.npy", a)
        z.writestr("__meta__.npy", meta)
    with pytest.raises(ArtefactError, match="checksum"):
        load_arrays(path, "rrtcolearn.test")


def test_pickle_bearing_file_is_refused(tmp_path):
    path = tmp_path / "evil.npz"
    marker = tmp_path / "executed"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    arr = np.empty(1, dtype=object)
    arr[0] = Evil()
    np.savez(path, a=arr, __meta__=np.array("{}"))
    assert b"executed" in path.read_bytes()  # the payload is in the file
    with pytest.raises(ArtefactError, match="unpickling"):
        load_arrays(path, "rrtcolearn.test")
    assert not marker.exists()


def test_object_arrays_are_never_written(tmp_path):
    with pytest.raises(TypeError):
        save_arrays(tmp_path / "x.npz", "f", {"a": np.array([None], dtype=object)}, {})


def test_wrong_format_and_version_are_refused(tmp_path):
    path = tmp_path / "a.npz"
    save_arrays(path, "rrtcolearn.other", {"a": np.zeros(2)}, {})
    with pytest.raises(ArtefactError, match="expected"):
        load_arrays(path, "rrtcolearn.test")
    meta = {"format": "rrtcolearn.test", "schema_version": 99, "sha256": digest({"a": np.zeros(2)})}
    np.savez(path, a=np.zeros(2), __meta__=np.array(json.dumps(meta)))
    with pytest.raises(ArtefactError, match="schema version"):
        load_arrays(path, "rrtcolearn.test")


def test_a_zip_version_zipfile_does_not_implement_is_a_clear_error(tmp_path):
    """A damaged header naming zip version 10.9 made zipfile raise NotImplementedError, which
    escaped as a traceback (found by the fuzz test)."""
    buf = io.BytesIO()
    np.savez(buf, a=np.arange(3))
    raw = bytearray(buf.getvalue())
    raw[raw.find(b"PK\x01\x02") + 6] = 109  # central directory: version needed to extract
    path = tmp_path / "d.npz"
    path.write_bytes(bytes(raw))
    with pytest.raises(ArtefactError, match="truncated or corrupt"):
        load_arrays(path, "rrtcolearn.dataset")


def test_random_bytes_are_no_pickle(tmp_path):
    """np.load takes any file that is neither a zip nor an .npy for a pickle: such a file
    is called damaged, not "data that would need unpickling"."""
    path = tmp_path / "functions.npz"
    path.write_bytes(np.random.default_rng(0).bytes(3000))
    with pytest.raises(ArtefactError, match="not a zip archive"):
        load_arrays(path, "x")


def test_write_errors_name_the_users_path(tmp_path, monkeypatch):
    target = tmp_path / "plan.json"
    (tmp_path / "dir").mkdir()
    with pytest.raises(IsADirectoryError, match="give a file name") as info:
        atomic_write_bytes(tmp_path / "dir", b"x")
    assert info.value.filename == str(tmp_path / "dir")

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(args[0]))

    monkeypatch.setattr(os, "open", refuse)
    with pytest.raises(PermissionError) as info:
        atomic_write_bytes(target, b"x")
    assert info.value.filename == str(target) and ".tmp" not in str(info.value)


def _member(raw: bytes, name: str) -> zipfile.ZipInfo:
    with zipfile.ZipFile(io.BytesIO(raw)) as z:
        return z.getinfo(name)


def _central_entry(raw: bytes, name: str) -> int:
    """Offset of ``name``'s central-directory record (signature PK\\x01\\x02)."""
    at = raw.find(b"PK\x01\x02")
    while at >= 0:
        n = int.from_bytes(raw[at + 28:at + 30], "little")
        if raw[at + 46:at + 46 + n] == name.encode():
            return at
        at = raw.find(b"PK\x01\x02", at + 4)
    raise AssertionError(f"{name} has no central-directory record")


def _refused_in_one_line(raw: bytes, path) -> str:
    path.write_bytes(raw)
    with pytest.raises(ArtefactError) as info:
        load_dataset(path)
    assert "\n" not in str(info.value)
    return str(info.value)


@pytest.mark.parametrize("member", ["sim_params.npy", "point_x1.npy", "__meta__.npy"])
def test_a_flag_bit_that_says_encrypted_is_an_artefact_error(small_dataset, tmp_path, member):
    """Bit 0 of a member's general-purpose flags (central directory, offset 8) marks it
    encrypted: zipfile raised RuntimeError "File 'sim_params.npy' is encrypted, password
    required for extraction", which escaped the loader as a traceback (issue 34; the fuzz
    test found it once in thousands of runs)."""
    path = tmp_path / "d.npz"
    save_dataset(path, small_dataset.take(slice(0, 200)), {"system": "pendulum"})
    raw = bytearray(path.read_bytes())
    at = _central_entry(bytes(raw), member)
    raw[at + 8] ^= 0x01
    message = _refused_in_one_line(bytes(raw), tmp_path / "damaged.npz")
    assert "truncated or corrupt" in message and "encrypted" in message


def test_a_damaged_npy_header_is_an_artefact_error(small_dataset, tmp_path):
    """A member too long for one read is parsed (its .npy header, by numpy through tokenize
    and ast) before zipfile reaches its CRC: an unclosed bracket raised tokenize.TokenError,
    which escaped the loader (found by bench/damage_fuzz.py: a flip in point_x1.npy)."""
    path = tmp_path / "d.npz"
    save_dataset(path, small_dataset, {"system": "pendulum"})
    raw = path.read_bytes()
    member = _member(raw, "point_x1.npy")
    assert member.file_size > 4096  # longer than zipfile's first read: the header comes first
    shape = raw.find(b"'shape': (", member.header_offset)
    close = raw.find(b")", shape)
    for at, byte in ((close, b" "), (raw.find(b"{", member.header_offset), b"}")):
        damaged = raw[:at] + byte + raw[at + 1:]
        message = _refused_in_one_line(damaged, tmp_path / "damaged.npz")
        assert "truncated or corrupt" in message


def test_a_header_that_is_not_an_npy_header_is_not_called_pickled(small_dataset, tmp_path):
    """numpy's ValueError for a header it cannot parse is damage, not a pickle refused."""
    path = tmp_path / "d.npz"
    save_dataset(path, small_dataset, {"system": "pendulum"})
    raw = path.read_bytes()
    at = raw.find(b"{'descr'", _member(raw, "point_x1.npy").header_offset)
    message = _refused_in_one_line(raw[:at] + b"[" + raw[at + 1:], tmp_path / "damaged.npz")
    assert "truncated or corrupt" in message and "unpickling" not in message


def _large_file(tmp_path) -> tuple:
    """A file whose members are read straight from the file (at least 1 MiB each, as a
    model's arrays are): float rows, a Fortran-ordered block and int32 row numbers."""
    from rrtcolearn.data.store import _DIRECT_BYTES

    rng = np.random.default_rng(5)
    arrays = {"points": rng.normal(size=(_DIRECT_BYTES // 40 + 7, 5)),
              "fortran": np.asfortranarray(rng.normal(size=(300, _DIRECT_BYTES // 2000))),
              "rows": rng.permutation(_DIRECT_BYTES // 3).astype(np.int32),
              "small": np.arange(4.0)}
    path = tmp_path / "large.npz"
    save_arrays(path, "rrtcolearn.test", arrays, {})
    return path, arrays


def test_large_members_read_as_np_load_reads_them(tmp_path, monkeypatch):
    path, arrays = _large_file(tmp_path)
    direct = []
    fromfile = np.fromfile
    monkeypatch.setattr(np, "fromfile", lambda *a, **k: direct.append(1) or fromfile(*a, **k))
    back, _ = load_arrays(path, "rrtcolearn.test")
    assert len(direct) == 3  # the three large members, straight from the file
    with np.load(path) as npz:  # the independent reference: numpy's own reader
        for name, a in arrays.items():
            ref = npz[name]
            assert back[name].dtype == ref.dtype and back[name].shape == ref.shape
            assert back[name].flags.f_contiguous == ref.flags.f_contiguous
            assert back[name].flags.writeable
            assert np.array_equal(back[name], ref) and np.array_equal(ref, a), name


@pytest.mark.parametrize("damage", ["data", "encrypted", "truncated", "shape", "compression"])
def test_damage_to_a_large_member_is_refused(tmp_path, damage):
    """A large member's bytes skip zipfile's CRC (`_read_stored`): a flipped data byte is
    caught by the digest, and the member's zip and .npy headers are still checked."""
    path, _ = _large_file(tmp_path)
    raw = bytearray(path.read_bytes())
    member = _member(bytes(raw), "points.npy")
    if damage == "data":
        raw[member.header_offset + member.file_size // 2] ^= 0x10
        match = "checksum"
    elif damage == "encrypted":
        raw[_central_entry(bytes(raw), "points.npy") + 8] ^= 0x01
        match = "encrypted"
    elif damage == "truncated":  # the central directory survives; the member's data not
        end = member.header_offset + member.file_size // 2
        raw = raw[:end] + raw[end + 4096:]
        match = "truncated or corrupt"
    elif damage == "shape":
        at = raw.find(b"'shape': (", member.header_offset) + len(b"'shape': (")
        raw[at] = ord("9") if raw[at] != ord("9") else ord("8")
        match = "truncated or corrupt|checksum"
    else:  # the central directory says deflated: zipfile's decompressor meets stored bytes
        raw[_central_entry(bytes(raw), "points.npy") + 10] = zipfile.ZIP_DEFLATED
        match = "truncated or corrupt"
    damaged = tmp_path / "damaged.npz"
    damaged.write_bytes(bytes(raw))
    with pytest.raises(ArtefactError, match=match) as info:
        load_arrays(damaged, "rrtcolearn.test")
    assert "\n" not in str(info.value)
