"""What a hostile live-view client costs the service's log: a real view, a real WebSocket client.

The Foxglove SDK logs an ERROR line per malformed frame and per unknown channel of a subscribe;
one subscribe message of 16 MiB made 130,000 lines (56 MB of log) from one connection.
"""

from __future__ import annotations

import json
import logging
import time

import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from service.keys import Keys
from service.live.foxview import SDK_LOG_BURST, FoxgloveView
from service.maps.book import MapBook

pytestmark = pytest.mark.integration


class _Kept(logging.Handler):
    """The records that reach the root logger's handlers (the service's log)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_a_subscribe_of_thousands_of_unknown_channels_costs_a_few_log_lines() -> None:
    kept = _Kept()
    logging.getLogger().addHandler(kept)
    view = FoxgloveView(0, "127.0.0.1", MapBook(1 << 20), Keys("rlutf"))
    view.start()
    try:
        assert view.url is not None
        subs = [{"id": i, "channelId": 100_000 + i} for i in range(5000)]
        url = view.url
        with connect(url, subprotocols=[Subprotocol("foxglove.sdk.v1")], max_size=None) as ws:
            for _ in range(20):
                ws.send("{not json")
            # the SDK then disconnects the client (its status messages fill its queue)
            ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline:  # drain the server's status messages
                try:
                    ws.recv(timeout=0.2)
                except (TimeoutError, ConnectionClosed):
                    break
            time.sleep(0.5)
        sdk = [r for r in kept.records if r.name.startswith("foxglove")]
        assert sdk, "the SDK logged nothing: the attack was not seen"
        # before: one line per unknown channel and per bad frame, 5020
        assert len(sdk) <= SDK_LOG_BURST
    finally:
        logging.getLogger().removeHandler(kept)
        view.close()
