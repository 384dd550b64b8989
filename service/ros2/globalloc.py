"""AMCL's ``reinitialize_global_localization`` service for ROS 2 robots, on rmw_zenoh's keys.

A ROS client (``ros2 service call /robot1/reinitialize_global_localization std_srvs/srv/Empty``,
or Nav2's own clients) sends a Zenoh query on the service's key,
``<domain>/<namespace>/reinitialize_global_localization/std_srvs::srv::dds_::Empty_/<hash>``,
with the request's CDR as payload and rmw_zenoh's attachment (``rmw_client_data.cpp``: target
``ALL_COMPLETE``, no consolidation). One queryable, declared complete as rmw_zenoh's services
are (``rmw_service_data.cpp``), answers every namespace and both hash namings: it turns the
request into a WIRE.md ``Relocalize`` on the robot's map, which takes the JSON
``relocalize`` input's path, and replies on the query's key with an ``Empty`` response and an
attachment carrying the request's sequence number and client GID, as rmw_zenoh's service does,
so the client matches it to its call. A robot with no map, or a query without rmw_zenoh's
attachment, gets an error reply and an Event.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import zenoh

from schemas import Relocalize
from service.config import Ros2Settings
from service.keys import InputKind, Message, printable
from service.ros2 import attachment, convert, names

log = logging.getLogger(__name__)

EMPTY_SRV = "std_srvs/srv/Empty"
#: ``std_srvs/srv/Empty_Response`` in CDR: the encapsulation header (little endian) and the
#: ``uint8 structure_needs_at_least_one_member`` rosidl adds to an empty message.
EMPTY_RESPONSE = b"\x00\x01\x00\x00\x00"
#: rmw_qos_profile_services_default: reliable, volatile, keep last 10.
SERVICE_QOS = names.Qos(depth=10)

Pass = Callable[[str, InputKind, bytes, Message], None]
"""Hand a validated input on (the front door's gate): robot, kind, JSON payload, message."""
Reject = Callable[[str | None, str, str, int], None]
"""Report bad input: robot (``None`` if unknown), key, what is wrong, receive time (ns)."""


class GlobalLocalization:
    """The queryable of ``reinitialize_global_localization`` in every namespace.

    Args:
        settings: the ``ros2`` settings (``global_localization_service`` names the service).
        put: where the Relocalize goes (the front door's odometry gate, then ``offer``).
        reject: where a refused call is reported.
        clock: receive times, ns since the epoch.
        overrides: namespace to robot id (``ros2.robots.NS.robot_id``).
    """

    def __init__(
        self,
        settings: Ros2Settings,
        put: Pass,
        reject: Reject,
        clock: Callable[[], int],
        overrides: dict[str, str],
    ) -> None:
        self.settings = settings
        self.put = put
        self.reject = reject
        self.clock = clock
        self.overrides = overrides
        self.calls = 0  # requests turned into a Relocalize
        self._queryable: Any = None

    @property
    def name(self) -> str | None:
        """The service's name relative to a robot's namespace (``None``: off)."""
        return self.settings.global_localization_service

    def start(self, session: zenoh.Session) -> None:
        """Declare the queryable (nothing when the service is off)."""
        if self.name is None:
            return
        key = f"{self.settings.domain_id}/**/{self.name.strip('/')}/{names.dds_type(EMPTY_SRV)}/*"
        self._queryable = session.declare_queryable(key, self._on_query, complete=True)

    def close(self) -> None:
        """Undeclare the queryable."""
        if self._queryable is not None:
            try:
                self._queryable.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
            self._queryable = None

    def _on_query(self, query: zenoh.Query) -> None:
        with query:
            try:
                self._answer(query)
            except Exception:  # a callback must never raise into zenoh
                log.exception(
                    "global localization request on %s failed", printable(str(query.key_expr))
                )

    def _answer(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        received = self.clock()
        s = self.settings
        dk = names.parse_data_key(key, s.domain_id)
        if dk is None or dk.msgtype != EMPTY_SRV:
            return
        try:
            robot = names.robot_of_namespace(dk.namespace, s.root_robot, self.overrides)
        except names.NamespaceError as err:
            self._refuse(query, None, key, str(err), received)
            return
        request = attachment.unpack(query.attachment.to_bytes()) if query.attachment else None
        if request is None:
            self._refuse(query, robot, key, "no rmw_zenoh attachment on the request", received)
            return
        map_id = s.robot(dk.namespace).map_id or s.map_id
        if map_id is None:
            ns = dk.namespace.strip("/") or "/"
            self._refuse(
                query,
                robot,
                key,
                f"no map to relocalize {robot} on: give ros2.map_id (--ros-map) or "
                f"ros2.robots.{ns}.map_id",
                received,
            )
            return
        msg = Relocalize(stamp_ns=received, map_id=map_id)
        self.put(robot, "relocalize", convert.wire_json(msg), msg)
        self.calls += 1
        log.info("robot %s: global localization on map %s requested over ROS 2", robot, map_id)
        reply = attachment.pack(request.sequence, self.clock(), request.gid)
        query.reply(key, EMPTY_RESPONSE, attachment=reply)

    def _refuse(
        self, query: zenoh.Query, robot: str | None, key: str, why: str, received: int
    ) -> None:
        self.reject(robot, key, f"{self.name}: {why}", received)
        query.reply_err(why.encode())
