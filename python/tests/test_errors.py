"""Bad input: each a documented Python exception with the library's message."""

from __future__ import annotations

import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

import strata


def test_the_exception_hierarchy() -> None:
    assert issubclass(strata.StoreError, strata.StrataError)
    assert issubclass(strata.StoreNotFoundError, strata.StoreError)
    assert issubclass(strata.DamagedStoreError, strata.StoreError)
    assert issubclass(strata.StoreInUseError, strata.StoreError)
    assert issubclass(strata.SourceError, strata.StrataError)
    assert issubclass(strata.StrataError, Exception)


def test_a_missing_store(tmp_path: pathlib.Path) -> None:
    with pytest.raises(strata.StoreNotFoundError, match="store does not exist"):
        strata.open(tmp_path / "nothing.strata")


def test_a_folder_that_is_not_a_store(tmp_path: pathlib.Path) -> None:
    with pytest.raises(strata.StoreNotFoundError, match="not a Strata store"):
        strata.open(tmp_path)


def small_store(path: pathlib.Path) -> pathlib.Path:
    a = np.random.default_rng(1).integers(0, 60000, size=(40, 40, 40), dtype=np.uint16)
    strata.from_numpy(a, dst=path).close()
    return path


def test_a_store_without_its_database(tmp_path: pathlib.Path) -> None:
    # Format 3: the records' pack files gone; refused at open, naming the store.
    store = small_store(tmp_path / "s.strata")
    shutil.rmtree(store / "packs")
    with pytest.raises(strata.StoreError) as caught:
        strata.open(store)
    assert str(store) in str(caught.value)


def test_a_store_with_damaged_bytes(tmp_path: pathlib.Path) -> None:
    # Garbage over the pack files' records: refused at open, or when a brick is read (its
    # checksum); either way a StoreError naming the store, never a crash.
    store = small_store(tmp_path / "s.strata")
    for f in sorted((store / "packs").rglob("*")):
        if f.is_file() and f.stat().st_size > 64:
            data = bytearray(f.read_bytes())
            for i in range(32, len(data), 97):
                data[i] ^= 0x5A
            f.write_bytes(bytes(data))
    with pytest.raises(strata.StoreError) as caught:
        vol = strata.open(store)
        vol.level(0)[...]
    assert str(store) in str(caught.value)


def test_a_store_read_by_another_process_opens_here_too(tmp_path: pathlib.Path) -> None:
    # Format 3 admits any number of readers (issue 48): another process holding the store
    # open does not keep this one out.
    store = small_store(tmp_path / "s.strata")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import strata, sys; v = strata.open(sys.argv[1]); print('open', flush=True); sys.stdin.read()", str(store)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "open"
        here = strata.open(store)
        assert here.level(0)[...].shape == here.level(0).shape
        here.close()
    finally:
        holder.communicate("")
    strata.open(store).close()


def test_one_process_opens_a_store_twice(tmp_path: pathlib.Path) -> None:
    store = small_store(tmp_path / "s.strata")
    a, b = strata.open(store), strata.open(store)
    np.testing.assert_array_equal(a[0], b[0])
    a.close()
    assert b[1].shape == (40, 40)
    b.close()
    with pytest.raises(strata.StoreError, match="closed"):
        b[0]


def test_import_of_a_missing_or_bad_file(tmp_path: pathlib.Path) -> None:
    with pytest.raises(strata.SourceError, match="cannot read"):
        strata.import_file(tmp_path / "absent.nii", tmp_path / "x.strata", progress=False)
    bad = tmp_path / "bad.nii"
    bad.write_bytes(b"\x00" * 400)
    with pytest.raises(strata.SourceError, match="bad.nii"):
        strata.import_file(bad, tmp_path / "y.strata", progress=False)
    with pytest.raises(strata.StoreError):
        strata.open(tmp_path / "y.strata")


def test_import_over_a_store_this_process_holds(tmp_path: pathlib.Path) -> None:
    store = small_store(tmp_path / "s.strata")
    vol = strata.open(store)
    with pytest.raises(strata.StoreError):
        strata.from_numpy(np.zeros((4, 4, 4), np.uint8), dst=store)
    assert vol[0, 0, 0] == vol[0, 0, 0]


def test_an_interrupted_import_leaves_no_store(tmp_path: pathlib.Path) -> None:
    # Ctrl-C during an import: the pending KeyboardInterrupt cancels it (the same path as an
    # exception from the progress callback, used here), and no complete store is left.
    calls = []

    def interrupt(done: int, total: int) -> None:
        calls.append(done)
        raise KeyboardInterrupt

    a = np.random.default_rng(4).integers(0, 65535, size=(256, 256, 256), dtype=np.uint16)
    dst = tmp_path / "cancelled.strata"
    try:
        strata.from_numpy(a, dst=dst, progress=interrupt)
    except KeyboardInterrupt:
        pass
    else:
        pytest.skip("the import finished before its first progress report (a fast machine)")
    assert calls
    with pytest.raises(strata.StoreError):
        strata.open(dst)
    assert not list(tmp_path.glob(".strata-from-numpy-*")), "the temporary raw file is removed"
