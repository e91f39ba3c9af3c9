"""Signals become exceptions inside `interruptible`, and are noticed even when swallowed."""

import os
import signal

import pytest

from bgs_batch.errors import Interrupted
from bgs_batch.signals import interruptible


class _SignalsInItsDestructor:
    """Sends SIGTERM while being destroyed: Python runs the handler inside ``__del__``, which
    ignores (prints) what it raises."""

    def __del__(self) -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(10_000):  # the handler runs at one of these bytecode boundaries
            pass


def test_a_signal_raises_interrupted_and_the_handlers_are_restored():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted, match="SIGTERM"), interruptible():
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(10_000):
            pass
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the swallowing
def test_a_signal_swallowed_by_a_destructor_is_still_noticed():
    reached = False
    with pytest.raises(Interrupted), interruptible() as interruption:
        victim = _SignalsInItsDestructor()
        del victim
        reached = True  # the destructor swallowed the handler's exception ...
        interruption.check()  # ... and the check raises it after all
    assert reached
