"""strata.serve: the data service on a thread of this process."""

from __future__ import annotations

import pathlib
import urllib.request

import numpy as np
import pytest

import strata


def test_serve_yields_urls_that_answer(tmp_path: pathlib.Path) -> None:
    a = np.arange(20 * 21 * 22, dtype=np.uint16).reshape(20, 21, 22)
    strata.from_numpy(a, dst=tmp_path / "one.strata").close()
    strata.from_numpy(a[::2], dst=tmp_path / "two.strata").close()
    with strata.serve(tmp_path, port=0) as urls:
        assert [u.rsplit("/", 1)[1] for u in urls] == ["one", "two"]
        assert all(u.startswith("http://127.0.0.1:") for u in urls)
        with urllib.request.urlopen(urls[0], timeout=10) as answer:
            assert answer.status == 200
            assert len(answer.read()) > 0
    with pytest.raises(OSError):
        urllib.request.urlopen(urls[0], timeout=2)


def test_serve_refuses_what_it_cannot_serve(tmp_path: pathlib.Path) -> None:
    with pytest.raises(strata.StoreError):
        strata.serve(tmp_path / "absent.strata")
    a = np.zeros((4, 4, 4), np.uint8)
    vol = strata.from_numpy(a, dst=tmp_path / "held.strata")
    # Format 3 admits many readers: a store open here can be served at the same time.
    with strata.serve(tmp_path / "held.strata") as urls:
        assert len(urls) == 1
    vol.close()
    with pytest.raises(strata.StrataError, match="token"):
        strata.serve(tmp_path / "held.strata", host="0.0.0.0")
    with strata.serve(tmp_path / "held.strata") as urls:
        assert len(urls) == 1
