"""A publisher's matching status: what ``psm replay --wait-subscribers`` and the lockstep arm wait
on before their first sample (zenoh's ``MatchingStatus`` object is always truthy)."""

from __future__ import annotations

import time

from services.bus.config import ZenohConfig
from services.bus.runtime import open_session, publisher_matching


def test_a_publisher_matches_only_once_a_subscriber_exists() -> None:
    session = open_session(ZenohConfig(mode="peer", multicast=False, listen=[], connect=[]))
    try:
        pub = session.declare_publisher("psmtest/matching/a")
        assert publisher_matching(pub) is False
        sub = session.declare_subscriber("psmtest/matching/**", lambda _s: None)
        deadline = time.monotonic() + 5.0
        while not publisher_matching(pub) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert publisher_matching(pub) is True
        sub.undeclare()
        deadline = time.monotonic() + 5.0
        while publisher_matching(pub) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert publisher_matching(pub) is False
    finally:
        session.close()


def test_a_publisher_without_a_matching_status_is_unknown() -> None:
    assert publisher_matching(object()) is None
