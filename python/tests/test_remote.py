"""strata.open(URL): a store served by strata serve (on loopback, started by the test) reads as
the same store read locally; tokens are sent, required, and never shown."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

import strata

TOKEN = "s3cret-token-0123456789abcdef"


@pytest.fixture(scope="module")
def served_array(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, pathlib.Path]:
    """An int16 array over several bricks per axis (3 levels), with a constant block, as a store."""
    rng = np.random.default_rng(11)
    a = rng.integers(-1000, 2000, size=(40, 70, 75), dtype=np.int16)
    a[0:32, 0:32, 0:32] = 5
    dst = tmp_path_factory.mktemp("remote") / "scan.strata"
    affine = np.diag([0.5, 0.75, 1.25, 1.0])
    affine[:3, 3] = [10.0, -20.0, 30.5]
    strata.from_numpy(a, affine=affine, dst=dst).close()
    return a, dst


def test_a_served_store_reads_as_the_local_one(served_array: tuple[np.ndarray, pathlib.Path]) -> None:
    a, dst = served_array
    local = strata.open(dst)
    with strata.serve(dst) as urls:
        remote = strata.open(urls[0])
        assert remote.kind == "served" and local.kind == "store"
        assert remote.url == urls[0] and remote.path is None
        assert remote.shape == local.shape == a.shape
        assert remote.spacing == local.spacing
        np.testing.assert_array_equal(remote.affine, local.affine)
        assert remote.dtype == local.dtype == np.int16
        assert remote.levels == local.levels == 3
        assert remote.level_shapes == local.level_shapes
        region = (slice(3, 37), slice(10, 69), slice(1, 74))
        got = remote.level(0)[region]
        np.testing.assert_array_equal(got, local.level(0)[region])
        np.testing.assert_array_equal(got, a[region])
        # Across the constant brick (no request) and a brick edge, at a coarser level too.
        np.testing.assert_array_equal(remote.level(0)[0:33, 0:40, 30], a[0:33, 0:40, 30])
        np.testing.assert_array_equal(remote.level(1)[...], local.level(1)[...])
        np.testing.assert_array_equal(np.asarray(remote.level(2)), np.asarray(local.level(2)))
        assert urls[0] in repr(remote) and urls[0] in repr(remote.level(1))
        remote.close()
    local.close()


def test_a_bad_token_is_a_token_error(served_array: tuple[np.ndarray, pathlib.Path]) -> None:
    a, dst = served_array
    with strata.serve(dst, token=TOKEN) as urls:
        with pytest.raises(strata.TokenError, match="requires a token.*token=") as missing:
            strata.open(urls[0])
        with pytest.raises(strata.TokenError, match="refused the token") as wrong:
            strata.open(urls[0], token="not-the-token-0123456789")
        for e in (missing, wrong):
            assert isinstance(e.value, strata.RemoteError)
            assert urls[0] in str(e.value) and TOKEN not in str(e.value)
        vol = strata.open(urls[0], token=TOKEN)
        np.testing.assert_array_equal(vol[5:9, 60:70, 70:75], a[5:9, 60:70, 70:75])
        assert TOKEN not in repr(vol) and TOKEN not in repr(vol.level(0)) and TOKEN not in vol.location
        vol.close()
    with pytest.raises(ValueError, match="token="):
        strata.open(dst, token=TOKEN)


def test_an_absent_store_or_server_is_named(served_array: tuple[np.ndarray, pathlib.Path]) -> None:
    _, dst = served_array
    with strata.serve(dst) as urls:
        base = urls[0].rsplit("/", 1)[0]
        with pytest.raises(strata.StoreNotFoundError, match="no store named 'absent'"):
            strata.open(base + "/absent")
        with pytest.raises(ValueError, match="token="):
            strata.open(urls[0].replace("http://", "http://user:pw@"))
    with pytest.raises(strata.StrataError, match="expected http://HOST:PORT"):
        strata.open("http://127.0.0.1:1/not/a/store")


def test_a_read_from_a_server_that_stopped_raises_instead_of_hanging(
    served_array: tuple[np.ndarray, pathlib.Path],
) -> None:
    a, dst = served_array
    server = strata.serve(dst)
    vol = strata.open(server.urls[0], timeout_s=2)
    np.testing.assert_array_equal(vol[0:2, 0:2, 0:2], a[0:2, 0:2, 0:2])
    server.stop()
    with pytest.raises(strata.RemoteError, match="giving up|did not answer"):
        vol.level(0)[:, 40:, 40:]
    vol.close()


def test_timeouts_are_checked() -> None:
    with pytest.raises(ValueError, match="timeout_s"):
        strata.open("http://127.0.0.1:1/v1/stores/a", timeout_s=-1)
    with pytest.raises(strata.RemoteError, match="cannot reach the server"):
        strata.open("http://127.0.0.1:1/v1/stores/a", timeout_s=0.5)
