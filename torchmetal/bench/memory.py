"""Peak resident memory of a block of work, measured inside a fresh child process.

tracemalloc does not see torch's allocator, so this reads the kernel's own high-water mark.
On Linux, writing ``5`` to ``/proc/self/clear_refs`` resets the peak (VmHWM, also what
``getrusage(...).ru_maxrss`` reports) to the current RSS, so the peak of one stage can be read
without the peaks of imports or data preparation that came before it. Where that file is not
writable, a 2 ms sampling thread (psutil or ``/proc/self/statm``) stands in.
"""

from __future__ import annotations

import os
import re
import resource
import threading
import time

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def current_rss() -> int:
    """Resident set size of this process in bytes."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * _PAGE
    except OSError:
        try:
            import psutil

            return int(psutil.Process().memory_info().rss)
        except ImportError:
            return peak_rss()


def peak_rss() -> int:
    """High-water resident set size of this process in bytes (VmHWM / ru_maxrss)."""
    try:
        with open("/proc/self/status") as f:
            m = re.search(r"VmHWM:\s+(\d+)\s+kB", f.read())
        if m:
            return int(m.group(1)) * 1024
    except OSError:
        pass
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


class PeakMemory:
    """Context manager: ``peak`` (bytes above the RSS at entry) and ``peak_abs`` after exit.

    >>> with PeakMemory() as pm:
    ...     work()
    >>> pm.peak
    """

    def __init__(self, interval: float = 0.002) -> None:
        self.interval = interval
        self.method = ""
        self.start = 0
        self.peak_abs = 0
        self.peak = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sampled = 0

    def _sample(self) -> None:
        while not self._stop.is_set():
            self._sampled = max(self._sampled, current_rss())
            time.sleep(self.interval)

    def __enter__(self) -> "PeakMemory":
        self.start = current_rss()
        if _reset_peak():
            self.method = "VmHWM after clear_refs"
        else:
            self.method = "sampled RSS"
            self._sampled = self.start
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self.peak_abs = max(self._sampled, current_rss())
        else:
            self.peak_abs = peak_rss()
        self.peak = max(self.peak_abs - self.start, 0)
