"""psfd.workers: independent calls on threads, in order, the first error raised once all have ended."""

from __future__ import annotations

import pytest

from psfd import workers
from psfd.errors import PairError


def test_concurrently_keeps_the_order_and_raises_the_first_error(monkeypatch):
    import threading
    import time

    seen = []

    def slow(value):
        time.sleep(0.05)
        seen.append(threading.get_ident())
        return value

    assert workers.concurrently(lambda: slow(1), lambda: slow(2), lambda: 3) == [1, 2, 3]
    monkeypatch.setattr(workers, "usable_cores", lambda: 2)
    finished = []

    def fails(message):
        time.sleep(0.02)
        finished.append(message)
        raise PairError(message)

    with pytest.raises(PairError, match="first"):
        workers.concurrently(lambda: fails("first"), lambda: fails("second"), lambda: finished.append("ok"))
    assert sorted(finished) == ["first", "ok", "second"]  # all ended before the error was raised
    monkeypatch.setattr(workers, "usable_cores", lambda: 1)
    seen.clear()
    assert workers.concurrently(lambda: slow("a"), lambda: slow("b")) == ["a", "b"]
    assert set(seen) == {threading.get_ident()}  # one core: all on this thread
