"""Generated arrays kept on disk (``nrc/io/disk_cache.py``), and the procedural clouds through it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nrc.io import disk_cache
from nrc.volume import procedural


@pytest.fixture
def root(tmp_path, monkeypatch):
    monkeypatch.setenv("NRC_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_an_entry_is_made_once_and_read_after(root, tmp_path):
    src = tmp_path / "maker.py"
    src.write_text("v1")
    calls = []

    def make():
        calls.append(1)
        return np.arange(6, dtype=np.float32).reshape(2, 3)

    a = disk_cache.cached_array("thing", (1, "x"), [src], make)
    b = disk_cache.cached_array("thing", (1, "x"), [src], make)
    assert len(calls) == 1 and np.array_equal(a, b) and b.dtype == np.float32
    disk_cache.cached_array("thing", (2, "x"), [src], make)  # other parameters: another entry
    src.write_text("v2")  # the code that makes it changed: another entry
    disk_cache.cached_array("thing", (1, "x"), [src], make)
    assert len(calls) == 3 and len(list((root / "thing").glob("*.npy"))) == 3


def test_a_corrupt_entry_is_made_again_with_a_warning(root, tmp_path):
    src = tmp_path / "maker.py"
    src.write_text("v1")
    make = lambda: np.ones(4, np.float32)  # noqa: E731
    disk_cache.cached_array("thing", (), [src], make)
    (path,) = (root / "thing").glob("*.npy")
    path.write_bytes(b"\x93NUMPY garbage")
    with pytest.warns(UserWarning, match="unreadable"):
        again = disk_cache.cached_array("thing", (), [src], make)
    assert np.array_equal(again, make())
    assert np.array_equal(np.load(path), make())  # and stored whole again


def test_off_keeps_nothing_and_an_unwritable_root_only_costs_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NRC_CACHE_DIR", "off")
    assert disk_cache.cache_root() is None
    assert disk_cache.cached_array("thing", (), [], lambda: np.zeros(2)).shape == (2,)
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("NRC_CACHE_DIR", str(blocker))
    assert disk_cache.cached_array("thing", (), [], lambda: np.zeros(3)).shape == (3,)


def test_procedural_clouds_come_from_the_cache_unchanged(root, monkeypatch):
    first = procedural.procedural_cloud(24, seed=3, kind="cumulus")
    assert len(list((root / "procedural").glob("*.npy"))) == 1

    def fail(*args):
        raise AssertionError("generated again")

    monkeypatch.setitem(procedural._GENERATORS, "cumulus", fail)
    again = procedural.procedural_cloud(24, seed=3, kind="cumulus")
    assert again.dtype == torch.float32 and torch.equal(again, first)
    with pytest.raises(AssertionError, match="generated again"):  # another seed is another cloud
        procedural.procedural_cloud(24, seed=4, kind="cumulus")


def test_an_atomic_write_that_fails_leaves_the_previous_file(tmp_path):
    """A write killed half-way (here: an exception after some bytes) leaves the file as it was and no temporary."""
    from nrc.io.atomic import write_atomically, write_text_atomically

    path = tmp_path / "made" / "memo.json"
    write_text_atomically(path, "one")

    def half(f):
        f.write(b"tw")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        write_atomically(path, half)
    assert path.read_text() == "one" and [p.name for p in path.parent.iterdir()] == ["memo.json"]
    write_atomically(path, lambda f: f.write(b"two"), fsync=True)
    assert path.read_text() == "two"
