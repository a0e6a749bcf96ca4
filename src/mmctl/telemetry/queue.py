"""A bounded single-producer queue whose ``put`` never blocks and counts what it drops.

The loop thread is the only producer and the publisher thread the only consumer.
``collections.deque.append``/``popleft`` are atomic under the GIL, and only the producer
ever makes the queue longer, so the length test in :meth:`DropQueue.put` cannot be
raced into overfilling it: no lock is taken on the hot path and the producer never
waits, whatever the consumer is doing (even when it is stuck).
"""

from __future__ import annotations

from collections import deque
from typing import Generic, TypeVar

T = TypeVar("T")


class DropQueue(Generic[T]):
    """Bounded FIFO: ``put`` appends or, when full, drops the *new* item and counts it.

    capacity: the most items held at once (> 0).  ``accepted`` and ``dropped`` are
    written by the producer only; ``taken`` by the consumer only.
    """

    __slots__ = ("_items", "accepted", "capacity", "dropped", "taken")

    def __init__(self, capacity: int):
        if capacity <= 0:
            raise ValueError(f"capacity must be > 0, got {capacity}")
        self.capacity = capacity
        self._items: deque[T] = deque()
        self.accepted = 0
        self.dropped = 0
        self.taken = 0

    def put(self, item: T) -> bool:
        """Enqueue ``item`` unless the queue is full; True if it was kept.  Never blocks."""
        if len(self._items) >= self.capacity:
            self.dropped += 1
            return False
        self._items.append(item)
        self.accepted += 1
        return True

    def drain(self, limit: int | None = None) -> list[T]:
        """Remove and return up to ``limit`` items (all queued ones if None), oldest first."""
        items = self._items
        n = len(items) if limit is None else min(limit, len(items))
        out = [items.popleft() for _ in range(n)]
        self.taken += n
        return out

    def __len__(self) -> int:
        return len(self._items)
