"""Resident memory of this process: what the stages report as their peak and the benchmarks
record per row (Linux ``/proc/self/status``; ``getrusage`` elsewhere)."""

from __future__ import annotations

__all__ = ["peak_rss_mb", "reset_peak_rss"]


def _status_kib(field_name: str) -> float | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field_name + ":"):
                    return float(line.split()[1])
    except OSError:
        return None
    return None


def reset_peak_rss() -> bool:
    """Reset the process's peak-RSS counter (Linux ``/proc/self/clear_refs``); True if it did."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float:
    """Peak resident memory of this process, MiB (since the last :func:`reset_peak_rss`)."""
    kib = _status_kib("VmHWM")
    if kib is None:  # pragma: no cover - non-Linux
        import resource

        kib = float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
    return kib / 1024.0
