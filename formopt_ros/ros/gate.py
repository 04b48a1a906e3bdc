"""Nothing published before it can be received: a node holds its first publication until each
of its publishers has matched the subscribers the run expects (the formation nodes that listen
to the topic, from the topic table, plus the recorders).

Streaming topics are volatile (a late subscriber gets live messages only), so this is what
makes a run start without losing a message to a subscriber, the recorder included, that was
still being discovered.
"""
from __future__ import annotations

import time
from typing import Any

from formopt_ros.wire.topics import BY_KEY


class PublisherGate:
    """Counts, per publisher, the matched subscriptions the run needs before it starts.

    Args:
        node: the node (for warnings while waiting).
        recorders: recorders (or other full subscribers) every publisher must reach too.
        followers: for leader topics, how many followers (each has a follower_sim and an
            estimator_planner) listen; 0 waits for the recorders only.
    """

    def __init__(self, node: Any, recorders: int, followers: int = 1) -> None:
        self.node = node
        self.recorders = recorders
        self.followers = followers
        self.required: list[tuple[Any, int]] = []
        self.open = False
        self._since = time.monotonic()
        self._warned = 0.0

    def add(self, publisher: Any, key: str) -> Any:
        """Gate ``publisher`` of topic-table ``key``; returns the publisher."""
        listeners = len(BY_KEY[key].listeners)
        per = self.followers if key.startswith('leader') else min(self.followers, 1)
        self.required.append((publisher, listeners * per + self.recorders))
        return publisher

    def missing(self) -> list[str]:
        """'topic: matched/required' of every publisher still short of subscribers."""
        return [f'{p.topic_name}: {p.get_subscription_count()}/{n}' for p, n in self.required
                if p.get_subscription_count() < n]

    def ready(self) -> bool:
        """True once every gated publisher has matched its subscribers (then stays True)."""
        if self.open:
            return True
        missing = self.missing()
        if not missing:
            self.open = True
            return True
        now = time.monotonic()
        if now - self._since > 5.0 and now - self._warned > 5.0:
            self._warned = now
            self.node.get_logger().warning('waiting for subscribers before the first message: '
                                           + ', '.join(missing))
        return False
