"""A store folder replaced under the running store (removed and made again, a backup copied in)
is claimed again, so a second `rlutf serve` on it is refused as on the folder it replaced."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest
import zenoh

from service.keys import Keys
from service.live.sessions import session_config
from service.maps import store as store_module
from service.maps.files import FileMapStore, StoreInUse
from service.maps.store import MapStorage


@pytest.mark.integration
def test_a_replaced_store_folder_is_claimed_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(store_module, "RETRY_S", 0.1)
    folder = tmp_path / "store"
    with zenoh.open(session_config("peer")) as session:
        said: list[str] = []
        storage = MapStorage(
            session, Keys(), FileMapStore(folder), 1_000_000, on_claim=lambda k, m: said.append(m)
        )
        try:
            shutil.rmtree(folder)
            folder.mkdir()
            time.sleep(0.5)
            with pytest.raises(StoreInUse):  # before, a second service took the folder
                FileMapStore(folder).claim()
            assert said == []

            # a second one that came first is said, once, and the store keeps trying
            shutil.rmtree(folder)
            folder.mkdir()
            second = FileMapStore(folder)
            try:
                assert second.claim()
            except StoreInUse:  # the store was quicker
                pytest.skip("the store claimed the new folder before the second one")
            time.sleep(0.5)
            assert len(said) == 1 and f"{folder} is served by another" in said[0], said
            assert "this process serves it too" in said[0]
            second.release()
            time.sleep(0.5)
            with pytest.raises(StoreInUse):
                FileMapStore(folder).claim()
            assert len(said) == 1
        finally:
            storage.close()
