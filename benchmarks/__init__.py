"""Benchmarks of kohpymc against reference samplers (``make bench``)."""

import os
import time


def cpu_seconds() -> float:
    """CPU seconds of this process and of its finished children (nutpie's chain processes).

    Examples
    --------
    >>> cpu_seconds() > 0
    True
    """
    children = os.times()
    return time.process_time() + children.children_user + children.children_system
