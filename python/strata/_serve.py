"""``strata.serve``: ``strata serve`` on a thread of this process."""

from __future__ import annotations

import os
from typing import Iterable

from . import _strata


class Server:
    """A running data service (``strata serve``) for some stores.

    ``with strata.serve(paths) as urls:`` yields the stores' URLs (a list, in the order the
    server lists them) and stops the server on leaving; :attr:`urls` and :meth:`stop` do the
    same without ``with``. A desktop viewer, the browser viewer or ``strata render`` opens the
    URLs. The server holds the stores: a store this process has open (:func:`strata.open`)
    cannot be served until that volume is closed.
    """

    def __init__(self, native: "_strata.NativeServer") -> None:
        self._native = native

    @property
    def base_url(self) -> str:
        """``http://HOST:PORT``."""
        return self._native.base_url

    @property
    def stores(self) -> dict[str, str]:
        """Served stores: name → URL."""
        return dict(self._native.stores())

    @property
    def urls(self) -> list[str]:
        """Every served store's URL."""
        return [url for _, url in self._native.stores()]

    def stop(self) -> None:
        """Stops the server (idempotent)."""
        self._native.stop()

    def __enter__(self) -> list[str]:
        return self.urls

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"<strata.Server {self.base_url}: {', '.join(self.stores)}>"


def serve(
    paths: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    port: int = 0,
    *,
    host: str = "127.0.0.1",
    token: str | None = None,
    web_viewer: str | os.PathLike[str] | None = None,
    frame_ancestors: str | None = None,
) -> Server:
    """Serves stores over HTTP as ``strata serve`` does: each path a store or a folder of
    stores; ``port=0`` picks a free port; loopback unless ``host`` says otherwise, which then
    needs a ``token`` (16 characters or more). Identifiers stay withheld.

    ``web_viewer`` is a folder with the browser viewer's files (``cargo run -p xtask -- web``
    writes them to ``web/dist/``), served at ``/``; ``frame_ancestors`` lists who may show
    that page in a frame (CSP sources such as ``http://localhost:*``; default nobody), which
    :class:`strata.Viewer` sets for its notebook.

    Raises a :class:`strata.StoreError` for a path that is not a servable store, and a
    :class:`strata.StrataError` when the address cannot be bound or the options are refused.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    viewer_dir = os.fspath(web_viewer) if web_viewer is not None else None
    return Server(
        _strata.serve(
            [os.fspath(p) for p in paths], port, host, token, viewer_dir, frame_ancestors
        )
    )
