"""Wall-clock time per named stage, summed over calls (per-stage figures in the job
logs and the benchmarks)."""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager


class StageClock:
    """``with clock("stage"): ...`` adds the block's wall-clock seconds to ``seconds["stage"]``."""

    def __init__(self, timer=time.perf_counter):
        self.seconds: dict[str, float] = defaultdict(float)
        self.timer = timer  # time.process_time: CPU time of the process instead

    @contextmanager
    def __call__(self, stage: str):
        started = self.timer()
        try:
            yield
        finally:
            self.seconds[stage] += self.timer() - started

    def summary(self, n_samples: int | None = None) -> str:
        """'stage 1.23 s (45 ns/sample), ...' in the order the stages first ran."""
        parts = []
        for stage, seconds in self.seconds.items():
            per_sample = f" ({1e9 * seconds / n_samples:.0f} ns/sample)" if n_samples else ""
            parts.append(f"{stage} {seconds:.2f} s{per_sample}")
        return ", ".join(parts)
