"""Worker processes for parallel runs: one place that says how they start.

Public API: `spawn_pool(jobs)`.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context


def spawn_pool(jobs: int) -> ProcessPoolExecutor:
    """A pool of `jobs` worker processes that are *spawned*, never forked: a fork of a process that has
    used OpenCV's thread pool (or holds zenoh, DDS or onnxruntime threads) can hang in its first OpenCV
    call (opencv/opencv#5150), so every benchmark, test campaign and renderer starts its workers fresh."""
    return ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"))
